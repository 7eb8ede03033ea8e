"""The controller's settings (`ControllerConfig`): card rules, validation, the kernel's
parameter row; the drive-side parameters of split mode."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxdrive.core.blocks import pll_gains
from fluxdrive.core.machine import (
    ConfigError,
    MachineCard,
    card_current_bandwidth_hz,
    required,
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
    CP_N,
    CP_OC_TRIP,
    CP_OS_TRIP,
    CP_P,
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
# machine by its physics, not by numbers bound to one motor.
CARD_RULES: dict[str, str] = {
    "current_bandwidth_hz": "PWM/10 (1.5-period delay), at least 3x the RL corner R/(2 pi L),"
    " at most PWM/5",
    "speed_bandwidth_hz": "0.015 x the card's current bandwidth (a target: the design's "
    "peaking limit may grant less)",
    "encoder_pll_hz": "0.15 x the card's current bandwidth",
    "speed_feedback_lpf_hz": "0.02 x the card's current bandwidth",
    "vdc_min_v": "0.28 x dc_bus_v",
    "vdc_max_v": "1.32 x dc_bus_v",
    "handover_rpm": "0.01 x rated speed",
    "handback_rpm": "2/3 of the card's handover speed",
    "if_accel_rpm_s": "0.2 x rated speed per second",
}
VDC_MIN_PU, VDC_MAX_PU = 0.28, 1.32
HANDOVER_PU, HANDBACK_OF_HANDOVER, IF_ACCEL_PU_S = 0.01, 2.0 / 3.0, 0.2
SPEED_OF_CURRENT_BW = 0.015  # speed-loop target / current-loop bandwidth (15 Hz at 1 kHz)


@dataclass
class ControllerConfig:
    """FOC settings; gains derive from bandwidths and the controller's own model of the
    machine (r_hat/l_hat/lambda_hat default to the machine card).  A field left None is
    derived from the machine card (CARD_RULES, `resolved`); a value set explicitly wins."""

    position_source: str = "encoder"  # 'encoder' or 'estimate'
    current_bandwidth_hz: float | None = None
    # target; the peaking limit may grant less (design_loops)
    speed_bandwidth_hz: float | None = None
    current_limit_pu: float = 2.0  # |i_q*| limit, per unit of rated current
    angle_advance_periods: float = 1.5
    deadtime_comp_s: float = 0.0
    decoupling: bool = True
    align_time_s: float = 0.15
    align_current_pu: float = 0.8
    if_current_pu: float = 1.0
    if_accel_rpm_s: float | None = None
    handover_rpm: float | None = None
    handback_rpm: float | None = None
    encoder_pll_hz: float | None = None
    speed_feedback_lpf_hz: float | None = None  # only for display/metrics, not in the loop
    # the driving observer's speed path, for the speed-loop design (set from the scenario's
    # driving observer; None: ideal feedback)
    speed_observer_pll_hz: float | None = None
    speed_observer_damping: float = 1.0
    speed_observer_lpf_hz: float = 0.0
    # robustness limit of the loop design: closed-loop peaking of every designed loop
    peak_limit_db: float = 3.0
    overcurrent_pu: float = 2.1  # instantaneous trip on any sampled phase current, pu of rated
    overspeed_pu: float = 1.5
    vdc_min_v: float | None = None
    vdc_max_v: float | None = None
    invalid_timeout_s: float = 0.05
    handover_dwell_s: float = 0.3  # estimate valid and agreeing with the ramp this long (the
    # paper observer's compensation frequency settles in ~0.3 s)
    # the I-f ramp at the handover speed this long without a handover latches "start-up
    # failed" (0: wait for ever); 5 s is many handover dwells and I-f load-angle periods
    handover_timeout_s: float = 5.0
    # handover criterion: 0 compares the estimate with the I-f ramp per sample (angle within
    # 70 deg, speed within 30 %); > 0 compares them low-passed at this cut-off, so the rotor's
    # undamped swing about the I-f vector (at light load) does not reset the dwell.  Keep it
    # well below that swing's frequency sqrt(p K_t I_if / J)/(2 pi) (about 23 Hz on the default
    # card at 0.6 pu) and its time constant below the dwell
    handover_agree_lpf_hz: float = 0.0
    i2t_limit_pu2s: float = 10.0  # I2t trip: integral of ((i/I_rated)^2-1) dt (150 % for 8 s)
    r_hat_ohm: float | None = None
    l_hat_h: float | None = None
    lambda_hat_vs: float | None = None
    # where the current loop runs: 'host' (the controller closes it on every sample and
    # sends duties) or 'split' (the drive closes it every PWM period on the host's current
    # references and angle; the host runs observers and speed loop at decimation x Ts)
    mode: str = "host"
    decimation: int = 1  # PWM periods per sample the host sees (split mode)
    # split mode, in-process: the host's answer to sample j reaches the drive this many
    # samples late (0: at the next sample boundary, the lockstep timing)
    host_delay_samples: int = 0
    # split mode: no reference this long while PWM is on -> PWM off, fault 'watchdog'
    reference_timeout_s: float = 0.01

    def resolved(self, card: MachineCard) -> ControllerConfig:
        """A copy with every unset card-derived field filled in from `card` (CARD_RULES)."""
        from dataclasses import replace

        kw: dict[str, Any] = {}
        # every rule reads the card only (never another field's explicit value), so setting
        # one bandwidth does not move the others
        cur = round(card_current_bandwidth_hz(card), 6)
        if self.current_bandwidth_hz is None:
            kw["current_bandwidth_hz"] = cur
        if self.speed_bandwidth_hz is None:
            kw["speed_bandwidth_hz"] = round(SPEED_OF_CURRENT_BW * cur, 6)
        if self.encoder_pll_hz is None:
            kw["encoder_pll_hz"] = 0.15 * cur
        if self.speed_feedback_lpf_hz is None:
            kw["speed_feedback_lpf_hz"] = 0.02 * cur
        if self.vdc_min_v is None:
            kw["vdc_min_v"] = round(VDC_MIN_PU * card.dc_bus_v, 9)
        if self.vdc_max_v is None:
            kw["vdc_max_v"] = round(VDC_MAX_PU * card.dc_bus_v, 9)
        if self.handover_rpm is None:
            kw["handover_rpm"] = HANDOVER_PU * card.rated_speed_rpm
        if self.handback_rpm is None:
            kw["handback_rpm"] = HANDBACK_OF_HANDOVER * HANDOVER_PU * card.rated_speed_rpm
        if self.if_accel_rpm_s is None:
            kw["if_accel_rpm_s"] = IF_ACCEL_PU_S * card.rated_speed_rpm
        return replace(self, **kw) if kw else self

    def validate(self, src: str = "control") -> ControllerConfig:
        """Every field checked for type and range; the message names the key and rule."""
        for key, (lo, hi) in CONTROL_RANGES.items():
            v = getattr(self, key)
            if v is None and (
                key in CARD_RULES
                or key.startswith(("r_hat", "l_hat", "lambda_hat", "speed_observer_pll"))
            ):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
                raise ConfigError(f"{src}: {key} must be a number in [{lo}, {hi}], got {v!r}")
        if not isinstance(self.decoupling, bool):
            raise ConfigError(f"{src}: decoupling must be true/false, got {self.decoupling!r}")
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
        vdc_min_v, vdc_max_v = (
            required(r.vdc_min_v, "vdc_min_v"),
            required(r.vdc_max_v, "vdc_max_v"),
        )
        if vdc_min_v >= vdc_max_v:
            raise ConfigError(
                f"{src}: vdc_min_v {r.vdc_min_v:g} V must be below vdc_max_v "
                f"{r.vdc_max_v:g} V (machine dc_bus_v {card.dc_bus_v:g} V)"
            )
        if required(r.current_bandwidth_hz, "current_bandwidth_hz") > (
            CURRENT_BW_MAX_OF_PWM * card.pwm_hz
        ):
            raise ConfigError(
                f"{src}: current_bandwidth_hz {r.current_bandwidth_hz} must not "
                f"exceed a quarter of the PWM frequency ({card.pwm_hz} Hz)"
            )
        if r.position_source not in ("encoder", "estimate"):
            raise ConfigError(
                f"{src}: position_source must be 'encoder' or 'estimate', got '{r.position_source}'"
            )
        if required(r.handback_rpm, "handback_rpm") >= required(r.handover_rpm, "handover_rpm"):
            raise ConfigError(
                f"{src}: handback_rpm ({r.handback_rpm:g}) must be below "
                f"handover_rpm ({r.handover_rpm:g}) (hysteresis)"
            )
        if r.mode not in CONTROL_MODES:
            raise ConfigError(f"{src}: mode must be one of {list(CONTROL_MODES)}, got {r.mode!r}")
        for key in ("decimation", "host_delay_samples"):
            if float(getattr(r, key)) != int(getattr(r, key)):
                raise ConfigError(f"{src}: {key} must be an integer, got {getattr(r, key)!r}")
        if r.mode == "host" and (r.decimation != 1 or r.host_delay_samples != 0):
            raise ConfigError(
                f"{src}: decimation and host_delay_samples apply to mode 'split' "
                f"(mode is 'host'; a decimated host-mode bench runs over CAN: docs/can.md)"
            )
        d = int(r.decimation)
        if r.reference_timeout_s < 2 * d * card.ts_s:
            raise ConfigError(
                f"{src}: reference_timeout_s {r.reference_timeout_s:g} s must be at least "
                f"two samples ({2 * d} PWM periods at decimation {d})"
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
        return cp


# the current loop's bandwidth is at most this share of the PWM frequency (check())
CURRENT_BW_MAX_OF_PWM = 0.25


def control_ranges(card: MachineCard, decimation: int = 1) -> dict[str, tuple[float, float]]:
    """CONTROL_RANGES with the limits that follow from the card and the (fixed) decimation
    -- the current loop's bandwidth at most a quarter of the PWM frequency, the reference
    timeout at least two of the host's samples -- so that a node's parameter descriptors
    say what check() accepts."""
    out = dict(CONTROL_RANGES)
    lo, hi = out["current_bandwidth_hz"]
    out["current_bandwidth_hz"] = (lo, min(hi, CURRENT_BW_MAX_OF_PWM * card.pwm_hz))
    lo, hi = out["reference_timeout_s"]
    out["reference_timeout_s"] = (max(lo, 2 * int(decimation) * card.ts_s), hi)
    return out


CONTROL_RANGES: dict[str, tuple[float, float]] = {
    "current_bandwidth_hz": (10.0, 5000.0),
    "speed_bandwidth_hz": (0.1, 200.0),
    "current_limit_pu": (0.05, 3.0),
    "angle_advance_periods": (0.0, 3.0),
    "deadtime_comp_s": (0.0, 1e-4),
    "align_time_s": (0.0, 10.0),
    "align_current_pu": (0.0, 2.0),
    "if_current_pu": (0.0, 2.0),
    "if_accel_rpm_s": (1.0, 1e5),
    "handover_rpm": (0.1, 1e5),
    "handback_rpm": (0.0, 1e5),
    "encoder_pll_hz": (1.0, 2000.0),
    "speed_feedback_lpf_hz": (0.1, 2000.0),
    "overcurrent_pu": (0.1, 5.0),
    "overspeed_pu": (0.1, 5.0),
    "vdc_min_v": (0.0, 1e4),
    "vdc_max_v": (1.0, 1e4),
    "invalid_timeout_s": (1e-4, 10.0),
    "handover_dwell_s": (0.0, 10.0),
    "handover_timeout_s": (0.0, 600.0),
    "handover_agree_lpf_hz": (0.0, 1000.0),
    "i2t_limit_pu2s": (0.01, 1e4),
    "r_hat_ohm": (0.0, 1e3),
    "l_hat_h": (1e-7, 10.0),
    "lambda_hat_vs": (1e-6, 10.0),
    "speed_observer_pll_hz": (0.1, 2000.0),
    "speed_observer_damping": (0.1, 5.0),
    "speed_observer_lpf_hz": (0.0, 2000.0),
    "peak_limit_db": (0.1, 20.0),
    "decimation": (1, 64),
    "host_delay_samples": (0, 1000),
    "reference_timeout_s": (1e-4, 10.0),
}
CONTROL_MODES = ("host", "split")

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


# what a split-mode drive accepts per DRIVE_PARAM ([lo, hi]; else OUT_OF_RANGE); the ones in
# DRIVE_PARAMS_STOPPED only while PWM is off (else NOT_WHILE_RUNNING)
DRIVE_PARAM_RANGES: dict[str, tuple[float, float]] = {
    "CUR_KP": (0.0, 1e4),
    "CUR_KI": (0.0, 1e8),
    "L_HAT": (1e-7, 10.0),
    "LAMBDA_HAT": (0.0, 10.0),
    "DECOUPLE": (0.0, 1.0),
    "VOLTAGE_ADVANCE": (0.0, 3.0),
    "DEADTIME_COMP_S": (0.0, 1e-4),
    "CUR_LIMIT_A": (0.01, 1e3),
    "REF_TIMEOUT_S": (1e-4, 10.0),
    "OVERCURRENT_A": (0.01, 1e3),
    "I2T_LIMIT_PU2S": (0.01, 1e4),
    "RATED_CURRENT_A": (0.01, 1e3),
    "VDC_MIN_V": (0.0, 1e4),
    "VDC_MAX_V": (1.0, 1e4),
    "HEARTBEAT_TIMEOUT_S": (0.0, 60.0),
    "POLE_PAIRS": (1.0, 64.0),
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
