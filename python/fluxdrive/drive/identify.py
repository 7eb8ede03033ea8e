"""Motor identification: R, L, lambda, J, friction and the inverter's deadtime voltage of the
motor on the bench, measured the way a drive's commissioning does it, written as a machine
card that runs the scenarios directly.

The procedure talks to the power stage through one small interface, `PlantLink`: apply a
duty (or PWM off) for one period, get the frame it produced (currents at the period's end,
the captured line voltages averaged over it, the bus voltage, the encoder).  `SimPlantLink`
is the switching-level plant in-process (sensor noise and quantisation on).

Steps (the card supplies what a nameplate gives: pole pairs, rated current and speed, bus,
PWM rate, sensor scales; everything else is measured):

  1. R and the deadtime voltage, at standstill: the rotor is aligned by a DC current along
     alpha, then held at several DC current levels with an open-loop voltage.  The captured
     (measured) voltage over the current gives R with the inverter's voltage error removed;
     the commanded voltage against the current is a line R i + (4/3) V_dt, whose intercept
     is the per-leg deadtime voltage V_dt = Vdc td / Ts.
  2. L, at standstill: a square-wave voltage around the DC bias (high-frequency injection,
     +-delta V); least squares of v - R i over di/dt, sample by sample (the EMF is zero).
  3. lambda, spinning in I-f (open loop, the controller's start-up ramp with no estimate):
     the back-EMF vector e = v - R i - L di/dt over the electrical speed, averaged.
  4. J and viscous friction, on the encoder: the speed loop at two speeds (B from the
     steady torque current), then a speed step with the current limit low so the drive
     accelerates at a known torque K_t i_q (J = (K_t i_q - B w)/(dw/dt)).

Guards (`IdentifySettings`, the command's --max-current-pu / --max-voltage-pu): every phase
current is checked each period against max_current_pu x the rated current (abort: PWM off,
IdentifyAbort); the standstill voltage commands are limited to max_voltage_pu x Vdc/sqrt(3);
PWM is off at the end, on an abort and on Ctrl-C (finally).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Protocol

import numpy as np

from fluxdrive.core.blocks import rng_new
from fluxdrive.core.machine import MachineCard, required
from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import markdown_table, param
from fluxdrive.core.transforms import clarke, line_to_phase
from fluxdrive.drive.control import (
    CO_DA,
    CO_DC,
    CO_EN,
    CO_IQ,
    CO_IQ_REF,
    CS_N,
    ControllerConfig,
    controller_reset,
    controller_step,
)
from fluxdrive.drive.observers import ES_N
from fluxdrive.drive.plant import (
    FR_DA,
    FR_DB,
    FR_ENC,
    FR_IA,
    FR_IB,
    FR_IC,
    FR_N,
    FR_VAB,
    FR_VBC,
    FR_VCA,
    FR_VDC,
    TR_N,
    machine_params,
    plant_advance,
    plant_initial_frame,
    plant_state,
)

RPM = 2 * math.pi / 60


@dataclass(frozen=True)
class IdentifySettings:
    """What `./fluxdrive identify` takes: the guards of the procedure and the simulated
    plant's seed."""

    # the procedure itself peaks at 0.89-0.91 pu (measured on default_spm and servo_320v):
    # a guard below the rated current would trip on it
    max_current_pu: float = param(
        1.2,
        unit="pu",
        doc="abort (PWM off) when a phase current exceeds this, of the card's rated current",
        range=(1.0, 3.0),
        live=False,
    )
    max_voltage_pu: float = param(
        0.5,
        unit="pu",
        doc="largest standstill voltage command (R, L steps), of Vdc/sqrt(3)",
        range=(0.02, 1.0),
        live=False,
    )
    seed: int = param(
        1,
        unit="-",
        doc="seed of the simulated plant's sensor noise",
        range=(0, 2**32 - 1),
        live=False,
    )


DOC_PAGE = ROOT / "docs" / "machines.md"  # its table of IdentifySettings


def docs_tables() -> dict[str, str]:
    """{block key: Markdown table} of the machines page (`./fluxdrive docs params`)."""
    return {"identify": markdown_table(IdentifySettings) + "\n"}


class IdentifyAbort(RuntimeError):
    """A guard tripped (over-current, ...): PWM is off; the message says why."""


class PlantLink(Protocol):
    """The power stage as identification sees it (in-process plant, CAN bench bridge)."""

    ts_s: float

    def step(self, duty: np.ndarray, enable: bool) -> np.ndarray:
        """Apply `duty` (3 values in [0, 1]) for one PWM period (PWM off if not `enable`);
        return the frame at its end (FR_* layout)."""

    def pwm_off(self) -> None:
        """Turn the PWM off (end, abort, Ctrl-C)."""


class SimPlantLink:
    """The switching-level plant in-process, sensors (noise, quantisation) on."""

    def __init__(self, card: MachineCard, seed: int = 1):
        self.card = card
        self.ts_s = card.ts_s
        self.mp = machine_params(card)
        self.pst = plant_state(0.3, 0.0, card.pole_pairs)  # rotor anywhere
        self.rng = rng_new(seed)
        self.frame = np.zeros(FR_N)
        self.truth = np.zeros(TR_N)
        self.load_t = np.array([0.0])
        self.load_y = np.array([0.0])
        self.load_cfg = np.array([0.0, 0.0])
        plant_initial_frame(self.pst, self.mp, self.rng, self.frame, self.truth)

    def step(self, duty: np.ndarray, enable: bool) -> np.ndarray:
        plant_advance(
            self.pst,
            self.mp,
            self.rng,
            np.ascontiguousarray(duty, dtype=float),
            bool(enable),
            self.load_t,
            self.load_y,
            self.load_cfg,
            self.frame,
            self.truth,
        )
        return self.frame.copy()

    def pwm_off(self) -> None:
        self.step(np.full(3, 0.5), False)


@dataclass
class Identified:
    resistance_ohm: float
    inductance_h: float
    flux_linkage_vs: float
    inertia_kgm2: float
    viscous_nms: float
    deadtime_v: float  # per-leg deadtime voltage Vdc td/Ts [V]
    deadtime_s: float

    def card(self, template: MachineCard, name: str | None = None) -> MachineCard:
        """The template card (nameplate, inverter, sensors) with the measured values."""
        return replace(
            template,
            name=name or template.name + "_identified",
            resistance_ohm=self.resistance_ohm,
            inductance_h=self.inductance_h,
            flux_linkage_vs=self.flux_linkage_vs,
            inertia_kgm2=self.inertia_kgm2,
            viscous_nms=self.viscous_nms,
            deadtime_s=self.deadtime_s,
        ).validate()


def _v_ab(fr: np.ndarray) -> tuple[float, float]:
    return clarke(*line_to_phase(fr[FR_VAB], fr[FR_VBC], fr[FR_VCA]))


def _i_ab(fr: np.ndarray) -> tuple[float, float]:
    return clarke(fr[FR_IA], fr[FR_IB], fr[FR_IC])


class Identifier:
    """Runs the steps on a PlantLink.  `template` gives the nameplate/inverter/sensor data;
    its R, L, lambda, J, B and deadtime are not used (only for nothing but defaults of the
    loop design before they are measured, which the steps replace in order)."""

    def __init__(
        self,
        link: PlantLink,
        template: MachineCard,
        settings: IdentifySettings = IdentifySettings(),
        progress: Callable[[str], None] | None = None,
    ):
        self.link = link
        self.tpl = template
        self.i_max = settings.max_current_pu * template.rated_current_a
        self.v_max = settings.max_voltage_pu * template.dc_bus_v / math.sqrt(3)
        self.say = progress or (lambda s: None)
        self.vdc = template.dc_bus_v

    # ---------------------------------------------------------------- primitives
    def _apply(self, duty: np.ndarray, enable: bool = True) -> np.ndarray:
        fr = self.link.step(duty, enable)
        peak = max(abs(fr[FR_IA]), abs(fr[FR_IB]), abs(fr[FR_IC]))
        if not math.isfinite(peak) or peak > self.i_max:
            self.link.pwm_off()
            raise IdentifyAbort(f"over-current {peak:.2f} A > {self.i_max:.2f} A: PWM off")
        if math.isfinite(fr[FR_VDC]) and fr[FR_VDC] > 1.0:
            self.vdc = float(fr[FR_VDC])
        return fr

    def _hold_alpha(self, v_alpha: float, n: int) -> np.ndarray:
        """Open-loop voltage along alpha for n periods (phase a +V, b and c -V/2)."""
        v = max(min(v_alpha, self.v_max), -self.v_max)
        x = 0.75 * v / self.vdc
        duty = np.array([0.5 + x, 0.5 - x, 0.5 - x])
        return np.array([self._apply(duty) for _ in range(n)])

    # ---------------------------------------------------------------- steps
    def _drive_to(self, i_target: float, pts: list[tuple[float, float]]) -> float:
        """Commanded alpha voltage for a DC current i_target: secant steps on the (current,
        voltage) points seen so far (the deadtime makes the line's intercept non-zero)."""
        ts = self.link.ts_s
        for _ in range(6):
            good = sorted(
                (p for p in pts if p[0] > 0.02 * self.tpl.rated_current_a),
                key=lambda p: abs(p[0] - i_target),
            )[:2]
            if len(good) == 2 and abs(good[0][0] - good[1][0]) > 1e-3:
                (i1, v1), (i2, v2) = good
                v = v1 + (v2 - v1) * (i_target - i1) / (i2 - i1)
            else:
                v = pts[-1][1] * 1.1
            v = min(v, self.v_max)
            fr = self._hold_alpha(v, int(0.05 / ts))[-int(0.01 / ts) :]
            i = float(np.mean([_i_ab(f)[0] for f in fr]))
            pts.append((i, v))
            if abs(i - i_target) < 0.03 * self.tpl.rated_current_a:
                break
        return v

    def resistance(self) -> tuple[float, float, float]:
        """(R, V_dt per leg, R from the captured voltages) from DC current levels along alpha
        at standstill."""
        ts = self.link.ts_s
        n_settle, n_meas = int(0.1 / ts), int(0.1 / ts)
        i_r = self.tpl.rated_current_a
        # creep the voltage up until a current flows (the rotor aligns onto alpha meanwhile)
        v = 0.005 * self.vdc
        pts: list[tuple[float, float]] = []
        for _ in range(80):
            fr = self._hold_alpha(v, int(0.02 / ts))[-20:]
            i = float(np.mean([_i_ab(f)[0] for f in fr]))
            pts.append((i, v))
            if i > 0.15 * i_r or v >= self.v_max:
                break
            v *= 1.15
        self.say(f"R: {v:.2f} V drives {i:.2f} A; aligning")
        self._hold_alpha(v, int(0.3 / ts))  # alignment settles
        rows = []
        for level in (0.3, 0.5, 0.7, 0.9):
            vv = self._drive_to(level * i_r, pts)
            frs = self._hold_alpha(vv, n_settle + n_meas)[n_settle:]
            i_a = np.array([_i_ab(f)[0] for f in frs])
            v_meas = np.array([_v_ab(f)[0] for f in frs])
            rows.append((float(np.mean(i_a)), float(np.mean(v_meas)), float(vv)))
            pts.append((rows[-1][0], vv))
            self.say(
                f"R: level {level:.1f} pu: i {rows[-1][0]:.3f} A, captured "
                f"{rows[-1][1]:.3f} V, commanded {vv:.3f} V"
            )
        i_l = np.array([r[0] for r in rows])
        r_meas = float(np.polyfit(i_l, [r[1] for r in rows], 1)[0])
        slope, icpt = np.polyfit(i_l, [r[2] for r in rows], 1)
        v_dt = float(icpt) * 0.75  # alpha-axis error (4/3) V_dt with a on +i, b and c on -i/2
        # R: the slope of the commanded voltage over the current levels (the deadtime's
        # constant voltage error drops out of the slope); the captured voltages' slope is a
        # cross-check (their capture quantisation is not dithered at a steady duty)
        self.say(
            f"R = {slope:.4f} ohm (commanded voltage over 4 current levels; captured "
            f"voltages give {r_meas:.4f} ohm), deadtime voltage {v_dt:.3f} V per leg"
        )
        return float(slope), v_dt, r_meas

    def inductance(self, r: float, v_dt: float) -> float:
        """L from a square-wave voltage around a DC bias (standstill, aligned rotor)."""
        ts = self.link.ts_s
        i_r = self.tpl.rated_current_a
        bias = r * 0.5 * i_r + (4.0 / 3.0) * v_dt
        # amplitude: a current swing of ~0.2 rated over a half period of `half` PWM periods
        half = 10
        amp = 0.05 * r * i_r
        self._hold_alpha(bias, int(0.1 / ts))  # settle at the bias first
        for _ in range(12):  # find an amplitude that swings the current ~0.2 rated
            frs = np.concatenate(
                [self._hold_alpha(bias + amp, half), self._hold_alpha(bias - amp, half)] * 3
            )
            i_a = np.array([_i_ab(f)[0] for f in frs])
            swing = float(np.ptp(i_a[-2 * half :]))
            if swing > 0.15 * i_r or amp >= 0.5 * self.v_max:
                break
            amp = min(amp * 1.6, 0.5 * self.v_max)
        n_cycles = int(0.3 / ts / (2 * half))
        frs = np.concatenate(
            [
                np.concatenate(
                    [self._hold_alpha(bias + amp, half), self._hold_alpha(bias - amp, half)]
                )
                for _ in range(n_cycles)
            ]
        )
        i_a = np.array([_i_ab(f)[0] for f in frs])
        v_a = np.array([_v_ab(f)[0] for f in frs])
        di = np.diff(i_a) / ts
        y = v_a[1:] - r * 0.5 * (i_a[1:] + i_a[:-1])
        # instrumental variable: the sign of the applied square wave (known, noise-free);
        # plain least squares would be biased low by the current noise in di/dt
        # (from the duty each frame says was applied: right on any link's latency)
        dd = frs[1:, FR_DA] - frs[1:, FR_DB]
        z = np.sign(dd - np.mean(dd))
        z = z - np.mean(z)
        lind = float(np.dot(z, y) / np.dot(z, di))
        self.say(f"L = {lind * 1e3:.4f} mH (square wave +-{amp:.2f} V, {n_cycles} cycles)")
        self.link.pwm_off()
        return lind

    def _controller(self, card: MachineCard, cfg: ControllerConfig):
        cp = cfg.to_params(card)
        cs = np.zeros(CS_N)
        controller_reset(cs)
        return cs, cp, np.zeros(15)

    def flux(self, r: float, lind: float) -> float:
        """lambda from the back-EMF while the controller's I-f start-up spins the rotor (no
        estimate ever valid, so it never hands over)."""
        ts = self.link.ts_s
        card = replace(self.tpl, resistance_ohm=r, inductance_h=lind)
        w_m = 0.2 * self.tpl.rated_speed_rad_s
        cfg = ControllerConfig(
            position_source="estimate", if_current_pu=0.5, speed_observer_pll_hz=25.0
        )
        cs, cp, out = self._controller(card, cfg)
        est = np.zeros(ES_N)
        t_ramp = 0.15 + w_m / RPM / required(cfg.resolved(card).if_accel_rpm_s, "if_accel_rpm_s")
        n_run, n_meas = int((t_ramp + 0.6) / ts), int(0.4 / ts)
        fr = self._apply(np.full(3, 0.5), False)
        e_mag = []
        i_prev = _i_ab(fr)
        for k in range(n_run):
            controller_step(cs, cp, fr, est, w_m, 0.0, out)
            fr = self._apply(out[CO_DA : CO_DC + 1], out[CO_EN] > 0.5)
            i_now = _i_ab(fr)
            if k >= n_run - n_meas:
                va, vb = _v_ab(fr)
                ea = va - r * 0.5 * (i_now[0] + i_prev[0]) - lind * (i_now[0] - i_prev[0]) / ts
                eb = vb - r * 0.5 * (i_now[1] + i_prev[1]) - lind * (i_now[1] - i_prev[1]) / ts
                e_mag.append(math.hypot(ea, eb))
            i_prev = i_now
            if k % int(0.25 / ts) == 0:
                self.say(f"lambda: I-f {min(k * ts / t_ramp, 1.0) * 100:3.0f} % of the ramp")
        self.link.pwm_off()
        lam = float(np.mean(e_mag)) / (w_m * self.tpl.pole_pairs)
        self.say(f"lambda = {lam * 1e3:.4f} mV s (back-EMF at {w_m / RPM:.0f} rpm in I-f)")
        return lam

    def mechanics(self, r: float, lind: float, lam: float) -> tuple[float, float]:
        """(J, B) on the encoder: steady torque current at two speeds, then a speed step at
        a low current limit (known accelerating torque)."""
        ts = self.link.ts_s
        kt = 1.5 * self.tpl.pole_pairs * lam
        j_guess = kt * self.tpl.rated_current_a * 0.05 / self.tpl.rated_speed_rad_s
        card = replace(
            self.tpl,
            resistance_ohm=r,
            inductance_h=lind,
            flux_linkage_vs=lam,
            inertia_kgm2=j_guess,
            viscous_nms=0.0,
        )
        lim_pu = 0.15
        cfg = ControllerConfig(position_source="encoder", current_limit_pu=lim_pu)
        cs, cp, out = self._controller(card, cfg)
        est = np.zeros(ES_N)
        cpr = 4.0 * self.tpl.encoder_lines
        w1, w2 = 0.05 * self.tpl.rated_speed_rad_s, 0.4 * self.tpl.rated_speed_rad_s
        fr = self._apply(np.full(3, 0.5), False)
        log: list[tuple[float, ...]] = []  # (t, encoder angle [rad], i_q, i_q*)

        def run(w_ref: float, seconds: float) -> None:
            nonlocal fr
            for _ in range(int(seconds / ts)):
                controller_step(cs, cp, fr, est, w_ref, 0.0, out)
                fr = self._apply(out[CO_DA : CO_DC + 1], out[CO_EN] > 0.5)
                log.append(
                    (len(log) * ts, fr[FR_ENC] / cpr * 2 * math.pi, out[CO_IQ], out[CO_IQ_REF])
                )

        def steady(t0: float, t1: float) -> tuple[float, float]:
            a = np.array([x for x in log if t0 <= x[0] < t1])
            w = np.polyfit(a[:, 0], a[:, 1], 1)[0]
            return float(w), float(np.mean(a[:, 2]))

        self.say("J, B: speed loop on the encoder, low speed")
        t_acc = w1 / (kt * lim_pu * self.tpl.rated_current_a / j_guess)
        run(w1, max(1.0, 3 * t_acc))
        t_a = log[-1][0]
        wa, iqa = steady(t_a - 0.4, t_a)
        self.say("J, B: speed step at the current limit")
        k0 = len(log)
        run(w2, 1.5)
        t_b = log[-1][0]
        wb, iqb = steady(t_b - 0.4, t_b)
        self.link.pwm_off()
        b = kt * (iqb - iqa) / (wb - wa)
        # momentum balance over the step: J (w(t2) - w(t1)) = integral of (K_t i_q - B w) dt,
        # with B w integrated as B (theta(t2) - theta(t1)); t1 just before the step, t2 at
        # the speed's peak (largest change); speeds from local fits of the encoder angle
        a = np.array(log)
        half = max(int(0.004 / ts), 5)

        def speed_at(k: int) -> float:
            sl = slice(max(k - half, 0), min(k + half, len(a)))
            return float(np.polyfit(a[sl, 0], a[sl, 1], 1)[0])

        k1 = k0 - half
        ws = [speed_at(k) for k in range(k0, len(a) - half, half)]
        k2 = k0 + half * int(np.argmax(ws))
        if ws[int(np.argmax(ws))] - wa < 0.5 * (w2 - w1):
            raise IdentifyAbort("the speed step did not happen; J unknown")
        w_1, w_2 = speed_at(k1), speed_at(k2)
        impulse = kt * float(np.sum(a[k1:k2, 2])) * ts - b * (a[k2, 1] - a[k1, 1])
        j = impulse / (w_2 - w_1)
        self.say(
            f"J: step {w_1:.2f} -> {w_2:.2f} rad/s in {(k2 - k1) * ts:.3f} s, "
            f"impulse {impulse:.4g} N m s"
        )
        self.say(f"J = {j:.4g} kg m^2, B = {b:.4g} N m s/rad")
        return float(j), float(max(b, 0.0))

    def run(self) -> Identified:
        try:
            r, v_dt, _ = self.resistance()
            lind = self.inductance(r, v_dt)
            lam = self.flux(r, lind)
            j, b = self.mechanics(r, lind, lam)
        finally:
            self.link.pwm_off()
        td = max(v_dt, 0.0) / (self.vdc * self.tpl.pwm_hz)
        return Identified(r, lind, lam, j, b, v_dt, td)


def identify_sim(
    card: MachineCard,
    seed: int | None = None,
    progress=None,
    settings: IdentifySettings = IdentifySettings(),
) -> tuple[Identified, float]:
    """Identify the simulated plant of `card` (seed: settings.seed unless given); returns
    (result, true per-leg V_dt)."""
    link = SimPlantLink(card, settings.seed if seed is None else seed)
    ident = Identifier(link, card, settings, progress=progress).run()
    return ident, card.dc_bus_v * card.deadtime_s * card.pwm_hz


def errors(ident: Identified, card: MachineCard) -> dict[str, float]:
    """Relative errors against the true card."""
    vdt = card.dc_bus_v * card.deadtime_s * card.pwm_hz
    return {
        "R": ident.resistance_ohm / card.resistance_ohm - 1,
        "L": ident.inductance_h / card.inductance_h - 1,
        "lambda": ident.flux_linkage_vs / card.flux_linkage_vs - 1,
        "J": ident.inertia_kgm2 / card.inertia_kgm2 - 1,
        "V_dt": ident.deadtime_v / vdt - 1 if vdt > 0 else float("nan"),
    }


TOLERANCE = {"R": 0.02, "L": 0.03, "lambda": 0.01, "J": 0.10, "V_dt": 0.10}


def _stderr(s: str) -> None:
    sys.stderr.write(f"[identify] {s}\n")
    sys.stderr.flush()


__all__ = [
    "Identified",
    "Identifier",
    "IdentifyAbort",
    "IdentifySettings",
    "PlantLink",
    "SimPlantLink",
    "identify_sim",
    "errors",
    "TOLERANCE",
    "asdict",
]
