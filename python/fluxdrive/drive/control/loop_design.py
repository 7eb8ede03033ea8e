"""Loop design of the FOC controller.

Loop design (`design_current_loop`): the textbook law K_p = L w_cc, K_i = R w_cc cancels the
RL pole; with the 1.5-period delay of a real digital drive the closed loop then peaks and its
-3 dB bandwidth overshoots the target.  So the gain is scaled until the *discrete* closed
loop (ZOH RL plant, one period of computation delay, the PI) has exactly the requested
-3 dB bandwidth.  The speed PI is designed the same way on J s + B with the current loop
approximated as its designed first-order bandwidth.

The one period is the timing of real timers (firmware/include/fd_hal.h): a duty computed in
the interrupt of sample k is written into the PWM timer's preload registers and applies from
the update event t_(k+1).  The in-process runner (host and split mode), the C drive core and
the SIL's timer model all keep that contract; `current_loop_margins` gives the phase and gain
margins of the designed loop with that delay (or with any other, e.g. host mode over CAN,
where the host's answer to sample k is written at k+1 and applies from k+2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fluxdrive.core.machine import (
    ConfigError,
    MachineCard,
)

# ====================================================================== design
DELAY_PERIODS = 1
"""Computation delay of the timing contract [PWM periods]: duty(k) acts over [k+1, k+2]."""


def current_open_loop(
    kp: float,
    ki: float,
    r: float,
    lind: float,
    ts: float,
    f_hz: np.ndarray,
    delay_periods: int = DELAY_PERIODS,
) -> np.ndarray:
    """Discrete open loop of the current PI at f: ZOH RL plant, `delay_periods` whole
    periods of computation delay, PI with forward-Euler integral (as controller_step)."""
    z = np.exp(1j * 2 * np.pi * np.asarray(f_hz, dtype=float) * ts)
    a = math.exp(-r * ts / lind)
    b = (1 - a) / r if r > 0 else ts / lind
    plant = b / (z - a) / z**delay_periods  # duty(k) acts over [k+d, k+d+1]
    ctrl = kp + ki * ts / (z - 1)  # integral term uses past errors (output, then update)
    return ctrl * plant


def _current_loop_tf(kp: float, ki: float, r: float, lind: float, ts: float, f_hz: np.ndarray):
    """Discrete closed loop i/i* at f (`current_open_loop` with the contract's delay)."""
    loop = current_open_loop(kp, ki, r, lind, ts, f_hz)
    return loop / (1 + loop)


def current_loop_margins(
    card: MachineCard,
    kp: float,
    ki: float,
    delay_periods: int = DELAY_PERIODS,
    r_hat: float | None = None,
    l_hat: float | None = None,
) -> dict[str, float]:
    """Phase margin [deg] at the gain crossover and gain margin [dB] at the -180 deg phase
    crossing of the current loop `current_open_loop` (PI `kp`, `ki` on the card's R, L, or
    the given estimates, at the card's PWM period), and the closed loop's -3 dB bandwidth;
    a margin the loop does not have below Nyquist is inf."""
    r = card.resistance_ohm if r_hat is None else r_hat
    lind = card.inductance_h if l_hat is None else l_hat
    ts = card.ts_s
    f = np.geomspace(1.0, 0.5 / ts * 0.9999, 20000)
    lo = current_open_loop(kp, ki, r, lind, ts, f, delay_periods)
    mag = np.abs(lo)
    ph = np.unwrap(np.angle(lo))
    pm = gm = math.inf
    fc = fp = math.nan
    cross = np.nonzero((mag[:-1] >= 1.0) & (mag[1:] < 1.0))[0]
    if cross.size:
        i = int(cross[0])
        pm = float(np.degrees(ph[i]) + 180.0)
        fc = float(f[i])
    pc = np.nonzero((ph[:-1] > -np.pi) & (ph[1:] <= -np.pi))[0]
    if pc.size:
        i = int(pc[0])
        gm = float(-20.0 * np.log10(mag[i]))
        fp = float(f[i])
    closed = lo / (1 + lo)
    below = np.nonzero(np.abs(closed) < 1 / math.sqrt(2))[0]
    return {
        "delay_periods": int(delay_periods),
        "phase_margin_deg": pm,
        "gain_margin_db": gm,
        "crossover_hz": fc,
        "phase_crossover_hz": fp,
        "bandwidth_hz": float(f[below[0]]) if below.size else math.inf,
    }


def _bandwidth_from_tf(tf_fn, f_lo: float, f_hi: float) -> float:
    f = np.geomspace(f_lo, f_hi, 4000)
    mag = np.abs(tf_fn(f))
    below = np.nonzero(mag < 1 / math.sqrt(2))[0]
    return float(f[below[0]]) if below.size else float(f_hi)


def _peak_db(tf_fn, f_lo: float, f_hi: float) -> float:
    """Largest closed-loop gain over [f_lo, f_hi] in dB (0 dB for a loop that never peaks)."""
    f = np.geomspace(f_lo, f_hi, 4000)
    return float(20.0 * np.log10(max(float(np.max(np.abs(tf_fn(f)))), 1e-300)))


def _largest_gain(
    bw_of, peak_of, target_hz: float, peak_limit_db: float, lo: float, hi: float
) -> tuple[float, bool]:
    """The one design rule of every loop: the gain scale g whose -3 dB bandwidth is the
    target, unless that peaks by more than the limit -- then the largest g that peaks by
    exactly the limit (the best the feedback path allows).  Returns (g, limited)."""
    a, b = lo, hi
    for _ in range(50):
        mid = 0.5 * (a + b)
        if bw_of(mid) < target_hz:
            a = mid
        else:
            b = mid
    g = 0.5 * (a + b)
    if peak_of(g) <= peak_limit_db:
        return g, False
    # peaking is not monotonic in g (too little gain leaves the PI's integral underdamped):
    # walk down from the target's gain to the first one within the limit, then refine
    grid = np.geomspace(g, lo, 60)
    peaks = [peak_of(x) for x in grid]
    ok = [i for i, pk in enumerate(peaks) if pk <= peak_limit_db]
    if not ok:  # nothing within the limit: the least peaking gain
        return float(grid[int(np.argmin(peaks))]), True
    a, b = float(grid[ok[0]]), float(grid[ok[0] - 1])
    for _ in range(30):
        mid = 0.5 * (a + b)
        if peak_of(mid) <= peak_limit_db:
            a = mid
        else:
            b = mid
    return a, True


def design_current_loop(
    card: MachineCard,
    bandwidth_hz: float,
    r_hat: float | None = None,
    l_hat: float | None = None,
    peak_limit_db: float = 3.0,
) -> tuple[float, float]:
    """(K_p [V/A], K_i [V/(A s)]) giving the requested -3 dB bandwidth of i_d/i_d*, or the
    highest the peaking limit allows (see `design_loops`)."""
    d = _design_current(card, bandwidth_hz, r_hat, l_hat, peak_limit_db)
    return d[0], d[1]


def _design_current(
    card: MachineCard,
    bandwidth_hz: float,
    r_hat: float | None,
    l_hat: float | None,
    peak_limit_db: float,
):
    r = card.resistance_ohm if r_hat is None else r_hat
    lind = card.inductance_h if l_hat is None else l_hat
    ts = card.ts_s
    w = 2 * math.pi * bandwidth_hz
    nyq = 0.5 / ts

    def tf(g: float):
        return lambda f: _current_loop_tf(g * lind * w, g * r * w, r, lind, ts, f)

    hi = 2.0
    if _bandwidth_from_tf(tf(hi), 1.0, nyq) < bandwidth_hz:
        raise ConfigError(
            f"current-loop bandwidth {bandwidth_hz} Hz is not reachable at "
            f"{card.pwm_hz} Hz PWM with the 1.5-period delay"
        )
    g, limited = _largest_gain(
        lambda g: _bandwidth_from_tf(tf(g), 1.0, nyq),
        lambda g: _peak_db(tf(g), 1.0, nyq),
        bandwidth_hz,
        peak_limit_db,
        0.05,
        hi,
    )
    return (
        g * lind * w,
        g * r * w,
        _bandwidth_from_tf(tf(g), 1.0, nyq),
        _peak_db(tf(g), 1.0, nyq),
        limited,
    )


def speed_feedback_tf(s: np.ndarray, pll_hz: float, damping: float, lpf_hz: float):
    """Speed estimate / true speed of a type-2 PLL's frequency (integrator) output,
    w_n^2/(s^2 + 2 zeta w_n s + w_n^2), times an optional first-order speed LPF."""
    wn = 2 * math.pi * pll_hz
    h = wn * wn / (s * s + 2 * damping * wn * s + wn * wn)
    if lpf_hz > 0:
        wl = 2 * math.pi * lpf_hz
        h = h * wl / (s + wl)
    return h


def speed_loop_tf(
    card: MachineCard,
    kp: float,
    ki: float,
    current_bw_hz: float,
    f_hz: np.ndarray,
    feedback_pll_hz: float | None = None,
    feedback_damping: float = 1.0,
    feedback_lpf_hz: float = 0.0,
    estimated: bool = False,
) -> np.ndarray:
    """Closed speed loop at f: plant K_t/(J s + B), current loop a first-order lag at its
    bandwidth, the PI acting on the speed estimate (the position source's PLL and LPF).
    True speed w/w* = F/(1 + F H); estimated speed w^/w* = F H/(1 + F H)."""
    s = 1j * 2 * np.pi * np.asarray(f_hz, dtype=float)
    wi = 2 * math.pi * current_bw_hz
    fwd = (
        (kp + ki / s)
        * card.torque_constant_nm_per_a
        / (card.inertia_kgm2 * s + card.viscous_nms)
        * wi
        / (s + wi)
    )
    h = (
        speed_feedback_tf(s, feedback_pll_hz, feedback_damping, feedback_lpf_hz)
        if feedback_pll_hz
        else 1.0
    )
    return fwd * h / (1 + fwd * h) if estimated else fwd / (1 + fwd * h)


def design_speed_loop(
    card: MachineCard,
    bandwidth_hz: float,
    current_bw_hz: float,
    zero_ratio: float = 0.25,
    feedback_pll_hz: float | None = None,
    feedback_damping: float = 1.0,
    feedback_lpf_hz: float = 0.0,
    peak_limit_db: float = 3.0,
) -> tuple[float, float]:
    """(K_p [A s/rad], K_i [A/rad]) of the speed PI: see `design_loops`."""
    d = _design_speed(
        card,
        bandwidth_hz,
        current_bw_hz,
        zero_ratio,
        feedback_pll_hz,
        feedback_damping,
        feedback_lpf_hz,
        peak_limit_db,
    )
    return d["kp"], d["ki"]


def _design_speed(
    card,
    bandwidth_hz,
    current_bw_hz,
    zero_ratio,
    feedback_pll_hz,
    feedback_damping,
    feedback_lpf_hz,
    peak_limit_db,
) -> dict:
    kt = card.torque_constant_nm_per_a
    j = card.inertia_kgm2
    wb = 2 * math.pi * bandwidth_hz
    fb = dict(
        feedback_pll_hz=feedback_pll_hz,
        feedback_damping=feedback_damping,
        feedback_lpf_hz=feedback_lpf_hz,
    )

    def gains(g: float) -> tuple[float, float]:
        # the whole PI scales with g: crossover ~ g w_b, integral zero at zero_ratio times it
        kp = g * j * wb / kt
        return kp, kp * g * wb * zero_ratio

    def tf(g: float, est: bool = False):
        kp, ki = gains(g)
        return lambda f: speed_loop_tf(card, kp, ki, current_bw_hz, f, estimated=est, **fb)

    def peak(g: float) -> float:
        # the robustness limit holds for what the encoder sees and for what the loop sees
        return max(_peak_db(tf(g), 0.01, 5e3), _peak_db(tf(g, True), 0.01, 5e3))

    g, limited = _largest_gain(
        lambda g: _bandwidth_from_tf(tf(g), 0.01, 5e3), peak, bandwidth_hz, peak_limit_db, 0.01, 5.0
    )
    kp, ki = gains(g)
    return {
        "kp": kp,
        "ki": ki,
        "bandwidth_hz": _bandwidth_from_tf(tf(g), 0.01, 5e3),
        "peak_db": _peak_db(tf(g), 0.01, 5e3),
        "est_bandwidth_hz": _bandwidth_from_tf(tf(g, True), 0.01, 5e3),
        "est_peak_db": _peak_db(tf(g, True), 0.01, 5e3),
        "limited": limited,
    }


@dataclass
class LoopDesign:
    """What `design_loops` chose and what the loop models predict for it."""

    kp_i: float  # current PI [V/A]
    ki_i: float  # [V/(A s)]
    current_bandwidth_hz: float  # achieved -3 dB of i/i*
    current_peak_db: float
    current_limited: bool  # True: the peaking limit, not the target, set the gain
    kp_w: float  # speed PI [A s/rad]
    ki_w: float  # [A/rad]
    speed_bandwidth_hz: float  # achieved -3 dB of the true speed w/w*
    speed_peak_db: float
    speed_est_bandwidth_hz: float  # of the estimated speed w^/w*
    speed_est_peak_db: float
    speed_limited: bool
    peak_limit_db: float

    def summary(self) -> str:
        lim = {True: " (peaking-limited)", False: ""}
        return (
            f"current loop {self.current_bandwidth_hz:.0f} Hz, peak "
            f"{self.current_peak_db:+.1f} dB{lim[self.current_limited]}; speed loop "
            f"{self.speed_bandwidth_hz:.1f} Hz true / {self.speed_est_bandwidth_hz:.1f} Hz "
            f"estimated, peak {max(self.speed_peak_db, self.speed_est_peak_db):+.1f} dB"
            f"{lim[self.speed_limited]} (limit {self.peak_limit_db:g} dB)"
        )


def design_loops(
    card: MachineCard,
    current_bw_hz: float = 1000.0,
    speed_bw_hz: float = 10.0,
    feedback_pll_hz: float | None = None,
    feedback_damping: float = 1.0,
    feedback_lpf_hz: float = 0.0,
    peak_limit_db: float = 3.0,
    r_hat: float | None = None,
    l_hat: float | None = None,
    zero_ratio: float = 0.25,
) -> LoopDesign:
    """The one design procedure for every drive's current and speed loops.

    Rule: each loop gets the gain that gives its target -3 dB bandwidth, unless the closed
    loop then peaks by more than `peak_limit_db` (3 dB: a phase margin of roughly 45 deg);
    then it gets the largest gain that peaks by exactly the limit.  So every position source
    gets the best gains its feedback path allows, and no bandwidth is a resonance.

    Current loop: K_p = g L w, K_i = g R w (the PI zero cancels the RL pole), the discrete
    closed loop (ZOH RL plant, one period of computation delay) evaluated for g.
    Speed loop: K_p = g J w_b/K_t, K_i = K_p g w_b zero_ratio (the PI zero stays at a fixed
    fraction of the crossover), on K_t/(J s + B) with the current
    loop as a first-order lag at its achieved bandwidth and the speed feedback through the
    position source's PLL (w_n^2/(s^2 + 2 zeta w_n s + w_n^2)) and speed LPF; the limit
    holds for both the true speed w/w* and the estimated speed w^/w*.  The -3 dB target
    is met on the true speed (what an encoder on the shaft measures)."""
    kp_i, ki_i, bw_i, pk_i, lim_i = _design_current(
        card, current_bw_hz, r_hat, l_hat, peak_limit_db
    )
    d = _design_speed(
        card,
        speed_bw_hz,
        bw_i,
        zero_ratio,
        feedback_pll_hz,
        feedback_damping,
        feedback_lpf_hz,
        peak_limit_db,
    )
    return LoopDesign(
        kp_i,
        ki_i,
        bw_i,
        pk_i,
        lim_i,
        d["kp"],
        d["ki"],
        d["bandwidth_hz"],
        d["peak_db"],
        d["est_bandwidth_hz"],
        d["est_peak_db"],
        d["limited"],
        peak_limit_db,
    )
