"""The controller's settings (`ControllerConfig`): card rules, validation, the kernel's
parameter row; the drive-side parameters of split mode."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxdrive.core.blocks import pll_gains
from fluxdrive.core.machine import (
    DEADTIME_RANGE_S,
    ConfigError,
    MachineCard,
    card_current_bandwidth_hz,
    required,
)
from fluxdrive.core.schema import (
    Limit,
    Rule,
    check_fields,
    check_limits,
    param,
    ranges,
    resolve,
    rule_texts,
)
from fluxdrive.drive.control.kernel import (
    CP_ADV,
    CP_AGREE_LPF,
    CP_ALIGN_I,
    CP_ALIGN_T,
    CP_DECOUPLE,
    CP_ENC_CPR,
    CP_ENC_KI,
    CP_ENC_KP,
    CP_HANDBACK,
    CP_HANDOVER,
    CP_HANDOVER_DWELL,
    CP_HANDOVER_TIMEOUT,
    CP_I2T_LIMIT,
    CP_IF_ACC,
    CP_IF_I,
    CP_IMAX,
    CP_INV_TIMEOUT,
    CP_IRATED,
    CP_KI_I,
    CP_KI_W,
    CP_KP_I,
    CP_KP_W,
    CP_L,
    CP_LAM,
    CP_LOCK_COS,
    CP_LOCK_LPF,
    CP_LOCK_MARGIN,
    CP_LOCK_TIMEOUT,
    CP_N,
    CP_OC_TRIP,
    CP_OS_TRIP,
    CP_P,
    CP_R,
    CP_REF_TIMEOUT,
    CP_SRC,
    CP_TDCOMP,
    CP_TS,
    CP_VDC_MAX,
    CP_VDC_MIN,
    CP_WFB_LPF,
    SRC_ENCODER,
    SRC_ESTIMATE,
)
from fluxdrive.drive.control.loop_design import (
    LoopDesign,
    design_loops,
)

# Per-unit rules that derive every unset ControllerConfig field from the machine card
# (`ControllerConfig.resolved`).  On the default card they give the values the testbed was
# tuned with (1 kHz current loop at 10 kHz PWM, 15 Hz speed-loop target, 20-95 V bus window,
# 30/20 rpm handover/hand-back at 3000 rpm rated), so a scenario carries over to another
# machine by its physics, not by numbers bound to one motor.  Every rule reads the card only
# (never another field's explicit value), so setting one bandwidth does not move the others.
VDC_MIN_PU, VDC_MAX_PU = 0.28, 1.32
HANDOVER_PU, HANDBACK_OF_HANDOVER, IF_ACCEL_PU_S = 0.01, 2.0 / 3.0, 0.2
SPEED_OF_CURRENT_BW = 0.015  # speed-loop target / current-loop bandwidth (15 Hz at 1 kHz)
# the current loop's bandwidth is at most this share of the PWM frequency (check())
CURRENT_BW_MAX_OF_PWM = 0.25
CONTROL_MODES = ("host", "split")


def _card_bw(card: MachineCard) -> float:
    return round(card_current_bandwidth_hz(card), 6)


def _rated_rpm(share: float) -> Rule:
    return Rule(
        f"{share:g} x rated speed" + (" per second" if share == IF_ACCEL_PU_S else ""),
        lambda card, cfg: share * card.rated_speed_rpm,
    )


_OF_CURRENT_BW = "the card's current bandwidth"
_PWM_QUARTER = Limit(
    "at most a quarter of the PWM frequency",
    lambda card, decimation: (None, CURRENT_BW_MAX_OF_PWM * card.pwm_hz),
)
_TWO_SAMPLES = Limit(
    "at least two samples (2 x decimation PWM periods)",
    lambda card, decimation: (2 * int(decimation) * card.ts_s, None),
)


@dataclass
class ControllerConfig:
    """FOC settings; gains derive from bandwidths and the controller's own model of the
    machine (r_hat/l_hat/lambda_hat default to the machine card).  A field left None is
    derived from the machine card (its card rule, `resolved`); a value set explicitly wins.
    Every field is declared once with its unit, range and text (`fluxdrive.core.schema`)."""

    position_source: str = param(
        "encoder",
        unit="",
        doc="angle/speed feedback: the encoder or the driving observer's estimate",
        choices=("encoder", "estimate"),
        live=False,
    )
    current_bandwidth_hz: float | None = param(
        None,
        unit="Hz",
        doc="-3 dB bandwidth of the dq current loops (gains re-designed)",
        range=(10.0, 5000.0),
        rule=Rule(
            "PWM/10 (1.5-period delay), at least 3x the RL corner R/(2 pi L), at most PWM/5",
            lambda card, cfg: _card_bw(card),
        ),
        limit=_PWM_QUARTER,
    )
    speed_bandwidth_hz: float | None = param(
        None,
        unit="Hz",
        doc="target -3 dB bandwidth of the speed loop (gains re-designed; lower if the "
        "peaking limit binds)",
        range=(0.1, 200.0),
        rule=Rule(
            f"{SPEED_OF_CURRENT_BW:g} x {_OF_CURRENT_BW} (a target: the design's peaking "
            "limit may grant less)",
            lambda card, cfg: round(SPEED_OF_CURRENT_BW * _card_bw(card), 6),
        ),
    )
    current_limit_pu: float = param(
        2.0, unit="pu", doc="|i_q*| limit, per unit of rated current", range=(0.05, 3.0)
    )
    angle_advance_periods: float = param(
        1.5, unit="periods", doc="inverse-Park angle advance, in periods of w^", range=(0.0, 3.0)
    )
    deadtime_comp_s: float = param(
        0.0, unit="s", doc="deadtime feed-forward on the duties (0 = off)", range=DEADTIME_RANGE_S
    )
    decoupling: bool = param(True, unit="", doc="cross-coupling and back-EMF feed-forward on")
    align_time_s: float = param(
        0.15, unit="s", doc="sensorless start: alignment time", range=(0.0, 10.0)
    )
    align_current_pu: float = param(
        0.8, unit="pu", doc="sensorless start: alignment d current", range=(0.0, 2.0)
    )
    if_current_pu: float = param(
        1.0, unit="pu", doc="sensorless start: I-f ramp current", range=(0.0, 2.0)
    )
    if_accel_rpm_s: float | None = param(
        None,
        unit="rpm/s",
        doc="sensorless start: I-f ramp acceleration",
        range=(1.0, 1e5),
        rule=_rated_rpm(IF_ACCEL_PU_S),
    )
    handover_rpm: float | None = param(
        None,
        unit="rpm",
        doc="I-f -> observer handover speed",
        range=(0.1, 1e5),
        rule=_rated_rpm(HANDOVER_PU),
    )
    handback_rpm: float | None = param(
        None,
        unit="rpm",
        doc="observer -> I-f hand-back speed (below handover)",
        range=(0.0, 1e5),
        rule=Rule(
            "2/3 of the card's handover speed",
            lambda card, cfg: HANDBACK_OF_HANDOVER * HANDOVER_PU * card.rated_speed_rpm,
        ),
    )
    encoder_pll_hz: float | None = param(
        None,
        unit="Hz",
        doc="encoder tracking-PLL bandwidth",
        range=(1.0, 2000.0),
        rule=Rule(f"0.15 x {_OF_CURRENT_BW}", lambda card, cfg: 0.15 * _card_bw(card)),
    )
    speed_feedback_lpf_hz: float | None = param(
        None,
        unit="Hz",
        doc="display low-pass of the speed feedback (metrics only, not in the loop)",
        range=(0.1, 2000.0),
        rule=Rule(f"0.02 x {_OF_CURRENT_BW}", lambda card, cfg: 0.02 * _card_bw(card)),
    )
    # the driving observer's speed path, for the speed-loop design (set from the scenario's
    # driving observer)
    speed_observer_pll_hz: float | None = param(
        None,
        unit="Hz",
        doc="driving observer's PLL bandwidth assumed by the speed-loop design; "
        "unset (0) = ideal feedback",
        range=(0.1, 2000.0),
        none_is_zero=True,
    )
    speed_observer_damping: float = param(
        1.0, unit="-", doc="driving observer's PLL damping assumed by the design", range=(0.1, 5.0)
    )
    speed_observer_lpf_hz: float = param(
        0.0,
        unit="Hz",
        doc="driving observer's speed LPF assumed by the design",
        range=(0.0, 2000.0),
    )
    peak_limit_db: float = param(
        3.0,
        unit="dB",
        doc="robustness limit of the loop design: closed-loop peaking of the current and "
        "speed loops",
        range=(0.1, 20.0),
    )
    overcurrent_pu: float = param(
        2.1,
        unit="pu",
        doc="instantaneous over-current trip on any sampled phase current, per unit of rated "
        "current",
        range=(0.1, 5.0),
    )
    overspeed_pu: float = param(
        1.5, unit="pu", doc="over-speed trip, per unit of rated speed", range=(0.1, 5.0)
    )
    vdc_min_v: float | None = param(
        None,
        unit="V",
        doc="DC-bus under-voltage trip",
        range=(0.0, 1e4),
        rule=Rule(
            f"{VDC_MIN_PU:g} x dc_bus_v", lambda card, cfg: round(VDC_MIN_PU * card.dc_bus_v, 9)
        ),
    )
    vdc_max_v: float | None = param(
        None,
        unit="V",
        doc="DC-bus over-voltage trip",
        range=(1.0, 1e4),
        rule=Rule(
            f"{VDC_MAX_PU:g} x dc_bus_v", lambda card, cfg: round(VDC_MAX_PU * card.dc_bus_v, 9)
        ),
    )
    invalid_timeout_s: float = param(
        0.05,
        unit="s",
        doc="loss-of-lock trip: estimate invalid this long in closed loop",
        range=(1e-4, 10.0),
    )
    # The back-EMF check (docs/engine.md, Protections): the observer's valid flag alone is
    # not trusted.  0.25 pu clears the measured-voltage errors at low speed (deadtime
    # residue and R^ error, about 0.1 pu on the default card at 150 % load) and stops a
    # runaway far below the over-speed trip.
    lock_emf_margin_pu: float = param(
        0.25,
        unit="pu",
        doc="loss-of-lock trip on the drive's own signals: the speed the back-EMF implies "
        "(frame voltages and currents in the estimate's frame) above 1.5 x the estimated "
        "speed plus this much, per unit of rated speed; 0: off",
        range=(0.0, 5.0),
    )
    lock_emf_angle_deg: float = param(
        60.0,
        unit="deg",
        doc="loss-of-lock trip: above lock_emf_margin_pu of speed, the back-EMF this far off "
        "the estimate's q axis",
        range=(10.0, 180.0),
    )
    lock_emf_lpf_hz: float = param(
        20.0, unit="Hz", doc="low-pass of the back-EMF check", range=(0.1, 1000.0)
    )
    lock_emf_timeout_s: float = param(
        0.1,
        unit="s",
        doc="loss-of-lock trip: the back-EMF disagreeing with the estimate this long",
        range=(1e-4, 10.0),
    )
    # 0.3 s: the paper observer's compensation frequency settles in ~0.3 s
    handover_dwell_s: float = param(
        0.3,
        unit="s",
        doc="estimate valid and agreeing with the I-f ramp this long before handover",
        range=(0.0, 10.0),
    )
    # 5 s is many handover dwells and I-f load-angle periods
    handover_timeout_s: float = param(
        5.0,
        unit="s",
        doc="I-f ramp at the handover speed this long without a handover latches 'start-up "
        "failed' (0 = wait for ever)",
        range=(0.0, 600.0),
    )
    # > 0 so the rotor's undamped swing about the I-f vector (at light load) does not reset
    # the dwell.  Keep it well below that swing's frequency sqrt(p K_t I_if / J)/(2 pi) (about
    # 23 Hz on the default card at 0.6 pu) and its time constant below the dwell
    handover_agree_lpf_hz: float = param(
        0.0,
        unit="Hz",
        doc="handover criterion: estimate vs I-f ramp (angle within 70 deg, speed within "
        "30 %) compared low-passed at this cut-off (0 = per sample)",
        range=(0.0, 1000.0),
    )
    i2t_limit_pu2s: float = param(
        10.0,
        unit="pu^2 s",
        doc="I2t trip: integral of ((i/I_rated)^2 - 1) dt (10: 150 % for 8 s)",
        range=(0.01, 1e4),
    )
    r_hat_ohm: float | None = param(
        None,
        unit="ohm",
        doc="controller's stator resistance R^",
        range=(0.0, 1e3),
        card_default="resistance_ohm",
    )
    l_hat_h: float | None = param(
        None,
        unit="H",
        doc="controller's stator inductance L^",
        range=(1e-7, 10.0),
        card_default="inductance_h",
    )
    lambda_hat_vs: float | None = param(
        None,
        unit="V s",
        doc="controller's magnet flux lambda^",
        range=(1e-6, 10.0),
        card_default="flux_linkage_vs",
    )
    mode: str = param(
        "host",
        unit="",
        doc="where the current loop runs: host (the controller closes it on every sample and "
        "sends duties) or split (the drive closes it every PWM period on the host's current "
        "references and angle; the host runs observers and speed loop at decimation x Ts)",
        choices=CONTROL_MODES,
        live=False,
    )
    decimation: int = param(
        1,
        unit="-",
        doc="PWM periods per sample the host sees (split mode)",
        range=(1, 64),
        live=False,
    )
    host_delay_samples: int = param(
        0,
        unit="samples",
        doc="split mode, in-process: the host's answer to sample j reaches the drive this "
        "many samples late (0: at the next sample boundary, the lockstep timing)",
        range=(0, 1000),
        live=False,
    )
    reference_timeout_s: float = param(
        0.01,
        unit="s",
        doc="split mode: the drive turns PWM off and latches 'watchdog' when no current "
        "reference comes for this long",
        range=(1e-4, 10.0),
        limit=_TWO_SAMPLES,
    )

    def resolved(self, card: MachineCard) -> ControllerConfig:
        """A copy with every unset card-derived field filled in from `card` (card rules)."""
        return resolve(self, card)

    def validate(self, src: str = "control") -> ControllerConfig:
        """Every field checked for type and range; the message names the key and rule."""
        check_fields(self, src)
        return self

    def design(self, card: MachineCard) -> LoopDesign:
        """The current and speed loops `design_loops` gives this drive: its own model of the
        machine, its position source's speed path, the peaking limit."""
        self = self.resolved(card)  # noqa: PLW0642 - the card fills what is unset
        lind = card.inductance_h if self.l_hat_h is None else self.l_hat_h
        r = card.resistance_ohm if self.r_hat_ohm is None else self.r_hat_ohm
        if self.position_source == "encoder":
            fb = (self.encoder_pll_hz, 1.0, 0.0)
        else:
            fb = (
                self.speed_observer_pll_hz,
                self.speed_observer_damping,
                self.speed_observer_lpf_hz,
            )
        return _cached_design(
            card,
            required(self.current_bandwidth_hz, "current_bandwidth_hz"),
            required(self.speed_bandwidth_hz, "speed_bandwidth_hz"),
            fb,
            self.peak_limit_db,
            r,
            lind,
        )

    def check(self, card: MachineCard, src: str = "control") -> ControllerConfig:
        """The settings resolved on `card` and checked as a whole (ranges, and the rules
        that tie fields to each other or to the card); returns the resolved copy."""
        r = self.validate(src).resolved(card).validate(src)
        check_limits(r, card, int(r.decimation), src)  # a quarter of PWM, two samples
        vdc_min_v, vdc_max_v = (
            required(r.vdc_min_v, "vdc_min_v"),
            required(r.vdc_max_v, "vdc_max_v"),
        )
        if vdc_min_v >= vdc_max_v:
            raise ConfigError(
                f"{src}: vdc_min_v {r.vdc_min_v:g} V must be below vdc_max_v "
                f"{r.vdc_max_v:g} V (machine dc_bus_v {card.dc_bus_v:g} V)"
            )
        if required(r.handback_rpm, "handback_rpm") >= required(r.handover_rpm, "handover_rpm"):
            raise ConfigError(
                f"{src}: handback_rpm ({r.handback_rpm:g}) must be below "
                f"handover_rpm ({r.handover_rpm:g}) (hysteresis)"
            )
        if r.mode == "host" and (r.decimation != 1 or r.host_delay_samples != 0):
            raise ConfigError(
                f"{src}: decimation and host_delay_samples apply to mode 'split' "
                f"(mode is 'host'; a decimated host-mode bench runs over CAN: docs/can.md)"
            )
        return r

    def to_params(self, card: MachineCard) -> np.ndarray:
        self = self.check(card)  # noqa: PLW0642 - the card fills what is unset
        cp = np.zeros(CP_N)
        lind = card.inductance_h if self.l_hat_h is None else self.l_hat_h
        lam = card.flux_linkage_vs if self.lambda_hat_vs is None else self.lambda_hat_vs
        d = self.design(card)
        kp_i, ki_i, kp_w, ki_w = d.kp_i, d.ki_i, d.kp_w, d.ki_w
        rpm = 2 * math.pi / 60
        cp[CP_TS] = card.ts_s
        cp[CP_P] = card.pole_pairs
        cp[CP_L] = lind
        cp[CP_LAM] = lam
        cp[CP_KP_I] = kp_i
        cp[CP_KI_I] = ki_i
        cp[CP_KP_W] = kp_w
        cp[CP_KI_W] = ki_w
        cp[CP_IMAX] = self.current_limit_pu * card.rated_current_a
        cp[CP_ADV] = self.angle_advance_periods
        cp[CP_TDCOMP] = self.deadtime_comp_s
        cp[CP_SRC] = SRC_ENCODER if self.position_source == "encoder" else SRC_ESTIMATE
        cp[CP_ALIGN_T] = self.align_time_s
        cp[CP_ALIGN_I] = self.align_current_pu * card.rated_current_a
        cp[CP_IF_I] = self.if_current_pu * card.rated_current_a
        cp[CP_IF_ACC] = required(self.if_accel_rpm_s, "if_accel_rpm_s") * rpm
        cp[CP_HANDOVER] = required(self.handover_rpm, "handover_rpm") * rpm
        cp[CP_HANDBACK] = required(self.handback_rpm, "handback_rpm") * rpm
        kp, ki = pll_gains(required(self.encoder_pll_hz, "encoder_pll_hz"), 1.0)
        cp[CP_ENC_KP] = kp
        cp[CP_ENC_KI] = ki
        cp[CP_ENC_CPR] = 4.0 * card.encoder_lines
        cp[CP_OC_TRIP] = self.overcurrent_pu * card.rated_current_a
        cp[CP_OS_TRIP] = self.overspeed_pu * card.rated_speed_rad_s
        cp[CP_VDC_MIN] = self.vdc_min_v
        cp[CP_VDC_MAX] = self.vdc_max_v
        cp[CP_DECOUPLE] = 1.0 if self.decoupling else 0.0
        cp[CP_WFB_LPF] = 2 * math.pi * required(self.speed_feedback_lpf_hz, "speed_feedback_lpf_hz")
        cp[CP_INV_TIMEOUT] = self.invalid_timeout_s
        cp[CP_HANDOVER_DWELL] = self.handover_dwell_s
        cp[CP_HANDOVER_TIMEOUT] = self.handover_timeout_s
        cp[CP_AGREE_LPF] = 2 * math.pi * self.handover_agree_lpf_hz
        cp[CP_I2T_LIMIT] = self.i2t_limit_pu2s
        cp[CP_IRATED] = card.rated_current_a
        cp[CP_REF_TIMEOUT] = self.reference_timeout_s
        cp[CP_R] = card.resistance_ohm if self.r_hat_ohm is None else self.r_hat_ohm
        cp[CP_LOCK_MARGIN] = self.lock_emf_margin_pu * card.rated_speed_rad_s * card.pole_pairs
        cp[CP_LOCK_COS] = math.cos(math.radians(self.lock_emf_angle_deg))
        cp[CP_LOCK_LPF] = 2 * math.pi * self.lock_emf_lpf_hz
        cp[CP_LOCK_TIMEOUT] = self.lock_emf_timeout_s
        return cp


# {field: text of the card rule that fills it when unset}
CARD_RULES: dict[str, str] = rule_texts(ControllerConfig)


# the drive-side parameters of split mode: DRIVE_PARAM prm_id name (config/can/fluxdrive.dbc)
# -> the controller row's field the drive reads (HEARTBEAT_TIMEOUT_S is the bridge's own)
DRIVE_PARAM_FIELDS: dict[str, int] = {
    "CUR_KP": CP_KP_I,
    "CUR_KI": CP_KI_I,
    "L_HAT": CP_L,
    "LAMBDA_HAT": CP_LAM,
    "DECOUPLE": CP_DECOUPLE,
    "VOLTAGE_ADVANCE": CP_ADV,
    "DEADTIME_COMP_S": CP_TDCOMP,
    "CUR_LIMIT_A": CP_IMAX,
    "REF_TIMEOUT_S": CP_REF_TIMEOUT,
    "OVERCURRENT_A": CP_OC_TRIP,
    "I2T_LIMIT_PU2S": CP_I2T_LIMIT,
    "RATED_CURRENT_A": CP_IRATED,
    "VDC_MIN_V": CP_VDC_MIN,
    "VDC_MAX_V": CP_VDC_MAX,
    "POLE_PAIRS": CP_P,
}


def _from_design(name: str) -> Rule:
    """Unset: what the host sends, the default controller's design on the card."""
    return Rule(
        "the host controller's design on the card (ControllerConfig.to_params)",
        lambda card, cfg: drive_param_values(ControllerConfig().to_params(card))[name],
    )


def _drive(doc: str, unit: str, rng: tuple[float, float], name: str) -> Any:
    return param(None, unit=unit, doc=doc, range=rng, rule=_from_design(name))


@dataclass
class DriveParams:
    """The drive-side parameters of split mode: DRIVE_PARAM over CAN (prm_id name = the field
    in upper case, config/can/fluxdrive.dbc), what a split-mode drive accepts (else
    OUT_OF_RANGE); the bench bridge's live parameters drive.<field>.  RATED_CURRENT_A and
    POLE_PAIRS are taken only while PWM is off (DRIVE_PARAMS_STOPPED, else NOT_WHILE_RUNNING)."""

    cur_kp: float | None = _drive("current PI proportional gain", "V/A", (0.0, 1e4), "CUR_KP")
    cur_ki: float | None = _drive("current PI integral gain", "V/(A s)", (0.0, 1e8), "CUR_KI")
    l_hat: float | None = _drive(
        "inductance of the drive's decoupling model", "H", (1e-7, 10.0), "L_HAT"
    )
    lambda_hat: float | None = _drive(
        "magnet flux of the drive's back-EMF feed-forward", "V s", (0.0, 10.0), "LAMBDA_HAT"
    )
    decouple: float | None = _drive(
        "1: cross-coupling and back-EMF feed-forward on, 0: off", "-", (0.0, 1.0), "DECOUPLE"
    )
    voltage_advance: float | None = _drive(
        "inverse-Park angle advance", "periods", (0.0, 3.0), "VOLTAGE_ADVANCE"
    )
    deadtime_comp_s: float | None = _drive(
        "deadtime feed-forward (0: off)", "s", DEADTIME_RANGE_S, "DEADTIME_COMP_S"
    )
    cur_limit_a: float | None = _drive(
        "limit of the current references the drive follows", "A", (0.01, 1e3), "CUR_LIMIT_A"
    )
    ref_timeout_s: float | None = _drive(
        "no HOST_REF this long with PWM on: PWM off, fault 'watchdog'",
        "s",
        (1e-4, 10.0),
        "REF_TIMEOUT_S",
    )
    overcurrent_a: float | None = _drive(
        "instantaneous over-current trip", "A", (0.01, 1e3), "OVERCURRENT_A"
    )
    i2t_limit_pu2s: float | None = _drive(
        "I2t trip: integral of ((i/I_rated)^2 - 1) dt", "pu^2 s", (0.01, 1e4), "I2T_LIMIT_PU2S"
    )
    rated_current_a: float | None = _drive(
        "rated current of the I2t protection (only with PWM off)",
        "A",
        (0.01, 1e3),
        "RATED_CURRENT_A",
    )
    vdc_min_v: float | None = _drive("DC-bus under-voltage trip", "V", (0.0, 1e4), "VDC_MIN_V")
    vdc_max_v: float | None = _drive("DC-bus over-voltage trip", "V", (1.0, 1e4), "VDC_MAX_V")
    # the bridge's own (not from the controller's row)
    heartbeat_timeout_s: float = param(
        0.0, unit="s", doc="host heartbeat timeout (0: off)", range=(0.0, 60.0)
    )
    pole_pairs: float | None = _drive(
        "pole pairs (only with PWM off)", "-", (1.0, 64.0), "POLE_PAIRS"
    )


# what a split-mode drive accepts per DRIVE_PARAM name ([lo, hi]; else OUT_OF_RANGE)
DRIVE_PARAM_RANGES: dict[str, tuple[float, float]] = {
    name.upper(): rng for name, rng in ranges(DriveParams).items()
}
DRIVE_PARAMS_STOPPED = ("POLE_PAIRS", "RATED_CURRENT_A")


def drive_param_values(cp: np.ndarray) -> dict[str, float]:
    """{DRIVE_PARAM name: value} the host sends a split-mode drive from its row `cp`."""
    return {name: float(cp[j]) for name, j in DRIVE_PARAM_FIELDS.items()}


_DESIGNS: dict[tuple, LoopDesign] = {}


def _cached_design(
    card: MachineCard,
    current_bw_hz: float,
    speed_bw_hz: float,
    fb: tuple,
    peak_limit_db: float,
    r: float,
    lind: float,
) -> LoopDesign:
    """design_loops, memoised on everything it reads (a scenario sweep re-uses a few)."""
    key = (
        card.ts_s,
        card.inertia_kgm2,
        card.viscous_nms,
        card.torque_constant_nm_per_a,
        current_bw_hz,
        speed_bw_hz,
        fb,
        peak_limit_db,
        r,
        lind,
    )
    if key not in _DESIGNS:
        _DESIGNS[key] = design_loops(
            card,
            current_bw_hz,
            speed_bw_hz,
            feedback_pll_hz=fb[0],
            feedback_damping=fb[1],
            feedback_lpf_hz=fb[2],
            peak_limit_db=peak_limit_db,
            r_hat=r,
            l_hat=lind,
        )
    return _DESIGNS[key]
