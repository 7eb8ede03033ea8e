"""What tripped a fault: the value, the limit and the setting the limit comes from."""

from __future__ import annotations

import math

import numpy as np

from fluxdrive.drive.control.kernel import (
    CP_HANDOVER_TIMEOUT,
    CP_I2T_LIMIT,
    CP_IF_I,
    CP_INV_TIMEOUT,
    CP_IRATED,
    CP_LAM,
    CP_LOCK_COS,
    CP_LOCK_MARGIN,
    CP_LOCK_TIMEOUT,
    CP_OC_TRIP,
    CP_OS_TRIP,
    CP_P,
    CP_SRC,
    CP_VDC_MAX,
    CP_VDC_MIN,
    CS_EMF_D,
    CS_EMF_MAG,
    CS_EMF_Q,
    CS_I2T,
    CS_LOCK_WHY,
    FAULT_BAD_SAMPLE,
    FAULT_LOSS_OF_LOCK,
    FAULT_NAMES,
    FAULT_OVERCURRENT,
    FAULT_OVERCURRENT_I2T,
    FAULT_OVERSPEED,
    FAULT_OVERVOLTAGE,
    FAULT_POSITION_INVALID,
    FAULT_START_FAILED,
    FAULT_UNDERVOLTAGE,
    LOCK_EMF_ANGLE,
    LOCK_EMF_SPEED,
    SRC_ESTIMATE,
)
from fluxdrive.drive.observers import ES_TH, ES_W
from fluxdrive.drive.plant import FR_ENC, FR_IA, FR_IB, FR_IC, FR_VDC, FRAME_COLUMNS


# ====================================================================== trips, explained
def trip_values(
    code: int,
    frame: np.ndarray,
    est: np.ndarray,
    cp: np.ndarray,
    cs: np.ndarray | None = None,
    w_fb_prev_rad_s: float = float("nan"),
) -> str:
    """What tripped fault `code` (the kernel records only the code): the value, the limit
    and the setting the limit comes from, e.g. '160.0 V > 95.0 V (control.vdc_max_v)'.
    `frame` is the frame the controller tripped on, `est` the driving estimate it saw
    (ES_*), `cs` its state (for the I2t integral), `w_fb_prev_rad_s` the mechanical speed
    feedback of the period before (an over-speed on the encoder)."""
    code = int(code)
    if code == FAULT_OVERVOLTAGE:
        return f"{frame[FR_VDC]:.1f} V > {cp[CP_VDC_MAX]:.1f} V (control.vdc_max_v)"
    if code == FAULT_UNDERVOLTAGE:
        return f"{frame[FR_VDC]:.1f} V < {cp[CP_VDC_MIN]:.1f} V (control.vdc_min_v)"
    if code == FAULT_OVERCURRENT:
        i = (frame[FR_IA], frame[FR_IB], frame[FR_IC])
        j = int(np.argmax(np.abs(i)))
        return (
            f"|i_{'abc'[j]}| {abs(i[j]):.2f} A > {cp[CP_OC_TRIP]:.2f} A (control."
            f"overcurrent_pu {cp[CP_OC_TRIP] / cp[CP_IRATED]:g} x {cp[CP_IRATED]:g} A)"
        )
    if code == FAULT_OVERCURRENT_I2T:
        val = f"{cs[CS_I2T]:.3g}" if cs is not None else "integral of ((i/I_rated)^2 - 1) dt"
        return (
            f"{val} > {cp[CP_I2T_LIMIT]:g} pu^2 s (control.i2t_limit_pu2s, I_rated "
            f"{cp[CP_IRATED]:g} A)"
        )
    if code == FAULT_OVERSPEED:
        rpm = 60.0 / (2 * math.pi)
        w = est[ES_W] / cp[CP_P] if cp[CP_SRC] == SRC_ESTIMATE else w_fb_prev_rad_s
        return f"{abs(w) * rpm:.0f} rpm > {cp[CP_OS_TRIP] * rpm:.0f} rpm (control.overspeed_pu)"
    if code == FAULT_LOSS_OF_LOCK:
        return _lock_values(est, cp, cs)
    if code == FAULT_START_FAILED:
        i_if = cp[CP_IF_I] / cp[CP_IRATED]
        return (
            f"no handover after {cp[CP_HANDOVER_TIMEOUT]:g} s at the handover speed "
            f"(control.handover_timeout_s): the estimate never agreed with the I-f ramp "
            f"for control.handover_dwell_s (a load above the torque of the I-f current, "
            f"{i_if:.2g} pu (control.if_current_pu), holds the rotor; or the observer "
            f"cannot see the rotor at this speed)"
        )
    if code == FAULT_POSITION_INVALID:
        return f"estimate not finite (theta^ = {est[ES_TH]}, omega^ = {est[ES_W]})"
    if code == FAULT_BAD_SAMPLE:
        bad = [
            f"{FRAME_COLUMNS[j]} = {frame[j]}"
            for j in (FR_IA, FR_IB, FR_IC, FR_VDC, FR_ENC)
            if not math.isfinite(frame[j])
        ]
        return ", ".join(bad) or "a value not finite"
    return "latched by the controller"


def _lock_values(est: np.ndarray, cp: np.ndarray, cs: np.ndarray | None) -> str:
    """Which loss-of-lock check tripped (CS_LOCK_WHY), with its numbers."""
    why = int(cs[CS_LOCK_WHY]) if cs is not None else -1
    rpm = 60.0 / (2 * math.pi) / cp[CP_P]  # electrical rad/s -> mechanical rpm
    after = f"for more than {cp[CP_LOCK_TIMEOUT]:g} s (control.lock_emf_timeout_s)"
    if why == LOCK_EMF_SPEED and cs is not None:
        w_emf = cs[CS_EMF_MAG] / cp[CP_LAM]
        w_est = abs(est[ES_W])
        return (
            f"the back-EMF implies {w_emf * rpm:.0f} rpm, the estimate says {w_est * rpm:.0f} "
            f"rpm (> 1.5 x estimate + {cp[CP_LOCK_MARGIN] * rpm:.0f} rpm, "
            f"control.lock_emf_margin_pu) {after}"
        )
    if why == LOCK_EMF_ANGLE and cs is not None:
        off = math.degrees(
            math.atan2(abs(cs[CS_EMF_D]), cs[CS_EMF_Q] * math.copysign(1, est[ES_W]))
        )
        limit = math.degrees(math.acos(cp[CP_LOCK_COS]))
        return (
            f"the back-EMF is {off:.0f} deg off the estimate's q axis (> {limit:.0f} deg, "
            f"control.lock_emf_angle_deg) {after}"
        )
    flag = (
        f"estimate flagged invalid (PLL error or |flux| out of bounds) for more than "
        f"{cp[CP_INV_TIMEOUT]:g} s in closed loop (control.invalid_timeout_s)"
    )
    if cs is None:  # the state is not at hand: either check may have tripped
        return f"{flag}, or the back-EMF disagreed with the estimate (control.lock_emf_*)"
    return flag


def describe_trip(
    code: int,
    frame: np.ndarray,
    est: np.ndarray,
    cp: np.ndarray,
    cs: np.ndarray | None = None,
    w_fb_prev_rad_s: float = float("nan"),
) -> str:
    """The fault's name and `trip_values`, e.g. 'DC-bus over-voltage 160.0 V > 95.0 V
    (control.vdc_max_v)'."""
    what = trip_values(code, frame, est, cp, cs, w_fb_prev_rad_s)
    sep = " " if what[:1].isdigit() or what[:1] == "|" else ": "
    return FAULT_NAMES.get(int(code), f"fault {int(code)}") + sep + what


def trip_message(t_s: float, detail: str) -> str:
    """'tripped at 0.000 s: <detail>' -- one line for logs, reports and metrics.json."""
    return f"tripped at {t_s:.3f} s: {detail}"
