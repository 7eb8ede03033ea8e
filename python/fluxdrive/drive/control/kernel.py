"""Field-oriented control kernels: dq current PI loops, speed PI, SVPWM, sensorless start-up.

Per PWM period (frame k in, duty out; the duty is applied over [t_{k+1}, t_{k+2}]):
  measure   Clarke/Park of the sampled currents at the position source's angle
  feedback  speed PI -> i_q*, current PIs with cross-coupling and back-EMF feed-forward
  output    inverse Park at theta + 1.5 Ts w (the voltage acts on average 1.5 periods
            later), SVPWM (min-max zero sequence) with the hexagon limit
  update    integrators back-calculated from the realised (limited) voltage.

Start-up without a position sensor (`position_source` = estimate): align (d-current at a
fixed angle), then an open-loop I-f ramp (current vector of fixed magnitude ON an angle
integrated from a ramped speed; the rotor follows at a load angle), handover to the observer
above `handover_speed` once its estimate is valid, and back to I-f below `handback_speed`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fluxdrive.core.blocks import lowpass_step, pi_output, pi_update, pll_step, pole
from fluxdrive.core.layout import Layout
from fluxdrive.core.protocol_constants import (
    FAULT_BAD_SAMPLE,
    FAULT_LOSS_OF_LOCK,
    FAULT_NONE,
    FAULT_OVERCURRENT,
    FAULT_OVERCURRENT_I2T,
    FAULT_OVERSPEED,
    FAULT_OVERVOLTAGE,
    FAULT_POSITION_INVALID,
    FAULT_STALE_INPUT,
    FAULT_START_FAILED,
    FAULT_UNDERVOLTAGE,
    FAULT_WATCHDOG,
)
from fluxdrive.core.transforms import TWO_PI, clarke, inv_clarke, inv_park, park, wrap_angle
from fluxdrive.drive.observers import ES_TH, ES_VALID, ES_W
from fluxdrive.drive.plant import (
    FR_ENC,
    FR_IA,
    FR_IB,
    FR_IC,
    FR_VAB,
    FR_VBC,
    FR_VCA,
    FR_VDC,
)

# ---- controller parameter vector CP_*
_CP = Layout("CP")
CP_TS = _CP.index()  # PWM period [s]
CP_P = _CP.index()  # pole pairs
CP_L = _CP.index()  # model inductance L^ [H]
CP_LAM = _CP.index()  # model flux linkage lambda^ [V s]
CP_KP_I = _CP.index()  # current PI proportional gain [V/A]
CP_KI_I = _CP.index()  # current PI integral gain [V/(A s)]
CP_KP_W = _CP.index()  # speed PI proportional gain [A s/rad]
CP_KI_W = _CP.index()  # speed PI integral gain [A/rad]
CP_IMAX = _CP.index()  # |i_q*| limit [A]
CP_ADV = _CP.index()  # angle advance of the output voltage [periods]
CP_TDCOMP = _CP.index()  # deadtime compensation [s]
CP_SRC = _CP.index()  # position source (SRC_*)
CP_ALIGN_T = _CP.index()  # alignment time [s]
CP_ALIGN_I = _CP.index()  # alignment d-current [A]
CP_IF_I = _CP.index()  # I-f current [A]
CP_IF_ACC = _CP.index()  # I-f ramp acceleration [rad/s^2 mechanical]
CP_HANDOVER = _CP.index()  # handover speed [rad/s mechanical]
CP_HANDBACK = _CP.index()  # hand-back speed [rad/s mechanical]
CP_ENC_KP = _CP.index()  # encoder PLL proportional gain [rad/s]
CP_ENC_KI = _CP.index()  # encoder PLL integral gain [rad/s^2]
CP_ENC_CPR = _CP.index()  # encoder counts per mechanical revolution
CP_OC_TRIP = _CP.index()  # instantaneous over-current trip [A]
CP_OS_TRIP = _CP.index()  # over-speed trip [rad/s mechanical]
CP_VDC_MIN = _CP.index()  # under-voltage trip [V]
CP_VDC_MAX = _CP.index()  # over-voltage trip [V]
CP_DECOUPLE = _CP.index()  # 1.0: cross-coupling and back-EMF feed-forward on
CP_WFB_LPF = _CP.index()  # display LPF of the speed feedback [rad/s]
CP_INV_TIMEOUT = _CP.index()  # estimate invalid this long in closed loop -> trip [s]
CP_HANDOVER_DWELL = _CP.index()  # estimate agreeing with the ramp this long -> handover [s]
CP_I2T_LIMIT = _CP.index()  # I2t trip [pu^2 s]
CP_IRATED = _CP.index()  # rated current [A]
CP_HANDOVER_TIMEOUT = _CP.index()  # at handover speed this long without handover -> trip [s]
CP_AGREE_LPF = _CP.index()  # handover agreement low-pass pole [rad/s]; 0: per sample
CP_REF_TIMEOUT = _CP.index()  # split mode: no reference this long with PWM on -> trip [s]
# loss of lock judged from the drive's own signals (the back-EMF check, _emf_lock)
CP_R = _CP.index()  # model resistance R^ [ohm]
CP_LOCK_MARGIN = _CP.index()  # implied speed over 1.5 |w^| by this much -> trip [rad/s el.]; 0 off
CP_LOCK_COS = _CP.index()  # cosine of the largest back-EMF angle off the estimate's q axis
CP_LOCK_LPF = _CP.index()  # low-pass pole of the back-EMF check [rad/s]
CP_LOCK_TIMEOUT = _CP.index()  # disagreement this long in closed loop -> trip [s]
CP_N = _CP.close(globals())
SRC_ENCODER, SRC_ESTIMATE = 0, 1

# ---- controller state CS_*
_CS = Layout("CS")
CS_MODE = _CS.index()  # MODE_*
CS_T_MODE = _CS.index()  # time in the current mode [s]
CS_ID_I, CS_IQ_I = _CS.indices(2)  # current PI integrators [V]
CS_W_I = _CS.index()  # speed PI integrator [A]
CS_TH_IF = _CS.index()  # I-f angle for the next period [rad]
CS_W_IF = _CS.index()  # I-f electrical speed [rad/s]
CS_ENC_TH = _CS.index()  # encoder PLL angle [rad]
CS_ENC_W = _CS.index()  # encoder PLL speed [rad/s]
CS_ENC_I = _CS.index()  # encoder PLL integrator [rad/s]
CS_ENC_INIT = _CS.index()  # 1 once the encoder PLL was seeded
CS_FAULT = _CS.index()  # latched fault code (FAULT_*)
CS_WFB_F = _CS.index()  # filtered speed feedback [rad/s mechanical]
CS_INV_T = _CS.index()  # time the estimate has been invalid [s]
CS_IQ_IF_F = _CS.index()  # filtered torque current in the observer's frame during I-f [A]
CS_AGREE_T = _CS.index()  # time the estimate has agreed with the ramp [s]
CS_I2T = _CS.index()  # I2t integral [pu^2 s]
CS_HO_WAIT_T = _CS.index()  # time the I-f ramp has waited at the handover speed [s]
CS_AG_C, CS_AG_S = _CS.indices(2)  # filtered unit vector of (estimate - I-f) angle
CS_AG_W = _CS.index()  # filtered (estimated - I-f) electrical speed [rad/s]
CS_EMF_D, CS_EMF_Q = _CS.indices(2)  # filtered back-EMF in the estimate's frame [V]
CS_EMF_MAG = _CS.index()  # filtered back-EMF magnitude [V]
CS_LOCK_T = _CS.index()  # time the back-EMF has disagreed with the estimate [s]
CS_LOCK_WHY = _CS.index()  # LOCK_* of the last disagreement (what a loss-of-lock trip saw)
CS_N = _CS.close(globals())
# why the lock was judged lost (CS_LOCK_WHY; fluxdrive.drive.control.trips explains each)
LOCK_OK, LOCK_INVALID, LOCK_EMF_SPEED, LOCK_EMF_ANGLE = range(4)

MODE_DISABLED, MODE_ALIGN, MODE_IF_RAMP, MODE_CLOSED_LOOP, MODE_FAULT = range(5)
MODE_NAMES = {0: "disabled", 1: "align", 2: "if_ramp", 3: "closed_loop", 4: "fault"}
FAULT_NAMES = {
    FAULT_NONE: "none",
    FAULT_OVERCURRENT: "over-current (instantaneous)",
    FAULT_OVERCURRENT_I2T: "over-current (I2t)",
    FAULT_OVERVOLTAGE: "DC-bus over-voltage",
    FAULT_UNDERVOLTAGE: "DC-bus under-voltage",
    FAULT_OVERSPEED: "over-speed",
    FAULT_LOSS_OF_LOCK: "loss of observer lock",
    FAULT_POSITION_INVALID: "position estimate not finite",
    FAULT_STALE_INPUT: "stale input",
    FAULT_WATCHDOG: "watchdog",
    FAULT_BAD_SAMPLE: "bad sample (NaN/inf)",
    FAULT_START_FAILED: "start-up failed",
}
"""The engine's fault codes (the DBC's fault_code table up to START_FAILED, the same numbers
as flux_drive_msgs/msg/DriveFault) with their descriptions."""

# ---- controller output CO_*
_CO = Layout("CO")
CO_DA, CO_DB, CO_DC = _CO.indices(3)  # duties for the next period
CO_EN = _CO.index()  # 1.0: PWM enabled
CO_ID, CO_IQ = _CO.indices(2)  # measured dq current [A]
CO_ID_REF, CO_IQ_REF = _CO.indices(2)  # dq current references [A]
CO_VD, CO_VQ = _CO.indices(2)  # realised dq voltage [V]
CO_W_REF = _CO.index()  # mechanical speed reference [rad/s]
CO_W_FB = _CO.index()  # mechanical speed feedback [rad/s]
CO_TH = _CO.index()  # angle the controller used [rad]
CO_MODE = _CO.index()  # MODE_*
CO_FAULT = _CO.index()  # fault code (FAULT_*)
CO_N = _CO.close(globals())

# ---- split mode (docs/can.md, split mode): the host's answer to sample j, RF_* -- what
# HOST_REF carries (current references, the angle at t_j and the speed) plus the host's
# mode and fault for the drive's record
_RF = Layout("RF")
RF_ID_REF, RF_IQ_REF = _RF.indices(2)  # dq current references [A]
RF_TH = _RF.index()  # electrical angle of the current frame at t_j [rad]
RF_W = _RF.index()  # electrical speed of the current frame [rad/s]
RF_EN = _RF.index()  # 1.0: PWM on
RF_MODE = _RF.index()  # the host's MODE_*
RF_FAULT = _RF.index()  # the host's latched FAULT_* (0: none)
RF_N = _RF.close(globals())

# ---- the drive's copy of the newest reference, DR_*
_DR = Layout("DR")
DR_ID_REF, DR_IQ_REF = _DR.indices(2)  # [A]
DR_TH = _DR.index()  # angle at the reference's sample instant t_j [rad]
DR_W = _DR.index()  # electrical speed [rad/s]
DR_EN = _DR.index()  # 1.0: PWM on
DR_MODE = _DR.index()  # the host's mode (recorded in CO_MODE)
DR_FAULT = _DR.index()  # the host's fault (recorded in CO_FAULT while PWM is off)
DR_DT = _DR.index()  # time from t_j to the current period's sample instant [s]
DR_AGE = _DR.index()  # time since the reference was taken [s]
DR_HAVE = _DR.index()  # 1.0 once a reference was taken
DR_N = _DR.close(globals())


@njit(cache=True)
def controller_reset(cs):
    for j in range(CS_N):
        cs[j] = 0.0
    cs[CS_MODE] = MODE_ALIGN


@njit(cache=True)
def controller_clear_fault(cs):
    """Explicit reset of a latched fault: back to the start-up sequence.  Returns the code
    that was cleared.  Faults are never cleared by anything else."""
    code = cs[CS_FAULT]
    if cs[CS_MODE] == MODE_FAULT:
        controller_reset(cs)
    return code


@njit(cache=True)
def _svpwm(va, vb, vdc):
    """Phase voltages -> duties, min-max zero sequence; beyond the hexagon the vector is
    scaled down (direction kept).  Returns (da, db, dc, scale)."""
    pa, pb, pc = inv_clarke(va, vb)
    hi = max(pa, pb, pc)
    lo = min(pa, pb, pc)
    span = hi - lo
    scale = 1.0
    if span > vdc:
        scale = vdc / span
        pa *= scale
        pb *= scale
        pc *= scale
        hi *= scale
        lo *= scale
    off = -0.5 * (hi + lo)
    return (0.5 + (pa + off) / vdc, 0.5 + (pb + off) / vdc, 0.5 + (pc + off) / vdc, scale)


@njit(cache=True)
def _trip(cs, out, code):
    """Latch `code` and write a complete PWM-off row: every CO_* field is set (zeros for
    the dq quantities, angle and feedback, which are not computed once tripped), so a
    reused output buffer never carries a stale value into a recording."""
    cs[CS_MODE] = MODE_FAULT
    cs[CS_FAULT] = code
    out[CO_DA] = 0.5
    out[CO_DB] = 0.5
    out[CO_DC] = 0.5
    out[CO_EN] = 0.0
    out[CO_ID] = 0.0
    out[CO_IQ] = 0.0
    out[CO_ID_REF] = 0.0
    out[CO_IQ_REF] = 0.0
    out[CO_VD] = 0.0
    out[CO_VQ] = 0.0
    out[CO_W_FB] = 0.0
    out[CO_TH] = 0.0
    out[CO_MODE] = MODE_FAULT
    out[CO_FAULT] = code


@njit(cache=True, inline="always")
def _protect(cs, cp, fr, out, ia, ib, ts):
    """Sample checks and trips (bad sample, over-current, I2t, bus voltage).  Returns True
    if the drive is (now) in fault; the PWM-off row is then already written."""
    vdc = fr[FR_VDC]
    ok = math.isfinite(fr[FR_IA]) and math.isfinite(fr[FR_IB]) and math.isfinite(fr[FR_IC])
    ok = ok and math.isfinite(vdc) and math.isfinite(fr[FR_ENC])
    if cs[CS_MODE] == MODE_FAULT:
        _trip(cs, out, cs[CS_FAULT])
        return True
    if not ok:
        _trip(cs, out, FAULT_BAD_SAMPLE)
        return True
    if max(abs(fr[FR_IA]), abs(fr[FR_IB]), abs(fr[FR_IC])) > cp[CP_OC_TRIP]:
        _trip(cs, out, FAULT_OVERCURRENT)
        return True
    # I2t: integrate (i/I_rated)^2 - 1 while above rated; trip at the configured pu^2 s
    i_pk2 = (ia * ia + ib * ib) / (cp[CP_IRATED] * cp[CP_IRATED])
    cs[CS_I2T] = max(cs[CS_I2T] + (i_pk2 - 1.0) * ts, 0.0)
    if cs[CS_I2T] > cp[CP_I2T_LIMIT]:
        _trip(cs, out, FAULT_OVERCURRENT_I2T)
        return True
    if vdc > cp[CP_VDC_MAX]:
        _trip(cs, out, FAULT_OVERVOLTAGE)
        return True
    if vdc < cp[CP_VDC_MIN]:
        _trip(cs, out, FAULT_UNDERVOLTAGE)
        return True
    return False


@njit(cache=True, inline="always")
def _encoder_feedback(cs, cp, fr, p, ts):
    """Encoder angle and speed through a tracking PLL (reference, encoder-mode feedback).
    Returns (angle of this sample [rad], PLL speed [rad/s electrical])."""
    th_enc_meas = wrap_angle(fr[FR_ENC] / cp[CP_ENC_CPR] * TWO_PI * p)
    if cs[CS_ENC_INIT] == 0.0:
        cs[CS_ENC_INIT] = 1.0
        cs[CS_ENC_TH] = th_enc_meas
    e_enc = math.sin(th_enc_meas - cs[CS_ENC_TH])
    w_enc, cs[CS_ENC_I], th_next = pll_step(
        cs[CS_ENC_TH], cs[CS_ENC_I], e_enc, cp[CP_ENC_KP], cp[CP_ENC_KI], ts
    )
    cs[CS_ENC_TH] = th_next
    return th_enc_meas, w_enc


@njit(cache=True, inline="always")
def _align(cs, cp):
    """Alignment: d-current ramped up at angle 0; then the I-f ramp.  Returns i_d* [A]."""
    frac = min(cs[CS_T_MODE] / (0.5 * cp[CP_ALIGN_T]), 1.0)
    id_ref = cp[CP_ALIGN_I] * frac
    if cs[CS_T_MODE] >= cp[CP_ALIGN_T]:
        cs[CS_MODE] = MODE_IF_RAMP
        cs[CS_T_MODE] = 0.0
        cs[CS_TH_IF] = 0.0
        cs[CS_W_IF] = 0.0
    return id_ref


@njit(cache=True, inline="always")
def _rotate_current_integrators(cs, angle):
    """The current PIs keep their integrators across a frame change: rotate them by angle."""
    cid, ciq = cs[CS_ID_I], cs[CS_IQ_I]
    cs[CS_ID_I] = cid * math.cos(angle) - ciq * math.sin(angle)
    cs[CS_IQ_I] = cid * math.sin(angle) + ciq * math.cos(angle)


@njit(cache=True, inline="always")
def _if_ramp(cs, cp, est, w_ref_m, id_inj, ia, ib, p, ts):
    """Open-loop I-f: the current vector sits on an angle integrated from a ramped speed; hand
    over to the observer once it agrees with the ramp.  Returns (theta, w_e, i_d*, mode)."""
    w_tgt = w_ref_m * p
    step = cp[CP_IF_ACC] * p * ts
    w_if = cs[CS_W_IF]
    if w_if < w_tgt - step:
        w_if += step
    elif w_if > w_tgt + step:
        w_if -= step
    else:
        w_if = w_tgt
    cs[CS_W_IF] = w_if
    th = cs[CS_TH_IF]
    cs[CS_TH_IF] = wrap_angle(th + w_if * ts)
    we = w_if
    # the current vector sits on the ramped angle (continuous with the alignment);
    # the rotor lags it by the load angle asin(T_L / (K_t I)), which pulls it along
    id_ref = cp[CP_IF_I] + id_inj
    hand = cp[CP_HANDOVER] * p
    # average torque current the rotor carries, seen in the observer's frame (5 Hz LPF):
    # the speed integrator starts from it at handover (an instantaneous sample would
    # kick the lightly damped rotor)
    _, iq_obs = park(ia, ib, math.cos(est[ES_TH]), math.sin(est[ES_TH]))
    cs[CS_IQ_IF_F] = lowpass_step(cs[CS_IQ_IF_F], iq_obs, pole(31.4, ts))
    # hand over only to an observer that agrees with the open-loop ramp: the rotor lags
    # the I-f vector by its load angle (< 90 deg) and turns at the ramp's speed
    d_th = est[ES_TH] - th
    d_w = est[ES_W] - w_if
    a_lpf = cp[CP_AGREE_LPF]
    if a_lpf > 0.0:
        # filtered agreement (control.handover_agree_lpf_hz): at light load the rotor swings
        # undamped about the I-f vector (speed +-50 % at no load), so a per-sample check is
        # reset by every swing although the estimate tracks the rotor; the mean load angle
        # and the mean speed of a rotor in step are the ramp's.  The angle difference is
        # filtered as a unit vector (no wrap); the filter restarts from each invalid sample
        # and on entering I-f (a hand-back must not reuse the agreement of an earlier start)
        if est[ES_VALID] == 0.0 or cs[CS_T_MODE] <= 1.5 * ts:
            cs[CS_AG_C], cs[CS_AG_S], cs[CS_AG_W] = math.cos(d_th), math.sin(d_th), d_w
        else:
            a = pole(a_lpf, ts)
            cs[CS_AG_C] = lowpass_step(cs[CS_AG_C], math.cos(d_th), a)
            cs[CS_AG_S] = lowpass_step(cs[CS_AG_S], math.sin(d_th), a)
            cs[CS_AG_W] = lowpass_step(cs[CS_AG_W], d_w, a)
        d_th = math.atan2(cs[CS_AG_S], cs[CS_AG_C])
        d_w = cs[CS_AG_W]
    agree = abs(wrap_angle(d_th)) < 1.22 and abs(d_w) < 0.3 * abs(w_if)
    if abs(w_if) >= hand and est[ES_VALID] != 0.0 and agree:
        cs[CS_AGREE_T] += ts
    else:
        cs[CS_AGREE_T] = 0.0
    # a start that cannot hand over (a load above the I-f current's torque pulls the rotor
    # out of step; an observer that never agrees) would ramp forever: a stated limit
    if abs(w_tgt) >= hand and abs(w_if) >= hand:
        cs[CS_HO_WAIT_T] += ts
        if cp[CP_HANDOVER_TIMEOUT] > 0.0 and cs[CS_HO_WAIT_T] > cp[CP_HANDOVER_TIMEOUT]:
            return th, we, id_ref, MODE_FAULT
    else:
        cs[CS_HO_WAIT_T] = 0.0
    if abs(w_tgt) >= hand and cs[CS_AGREE_T] >= cp[CP_HANDOVER_DWELL]:
        # handover: continue closed loop on the observer; the speed integrator starts
        # from the torque current the rotor is carrying in the observer's frame
        cs[CS_W_I] = cs[CS_IQ_IF_F]
        cs[CS_MODE] = MODE_CLOSED_LOOP
        cs[CS_T_MODE] = 0.0
        cs[CS_WFB_F] = est[ES_W] / p
        _rotate_current_integrators(cs, th - est[ES_TH])
        cs[CS_EMF_D] = 0.0  # the back-EMF check starts afresh on the observer's frame
        cs[CS_EMF_Q] = 0.0
        cs[CS_EMF_MAG] = 0.0
        cs[CS_LOCK_T] = 0.0
        return est[ES_TH], est[ES_W], id_ref, MODE_CLOSED_LOOP
    return th, we, id_ref, MODE_IF_RAMP


@njit(cache=True, inline="always")
def _hand_back(cs, cp, th, we, id_inj, ts):
    """Closed loop -> I-f below the hand-back speed.  The I-f vector takes over the torque
    the closed loop carried: it is placed ahead of (motoring) or behind (braking) the
    estimated rotor angle by the load angle asin(i_q/I_if), i_q the speed integrator's
    (steady) torque current, so the torque does not step to zero -- a step would kick the
    rotor into the I-f ramp's undamped load-angle oscillation.  Either sign of speed and
    torque; the angle is clipped at 64 deg (the I-f stiffness vanishes at 90).
    Returns (theta, i_d*)."""
    s_ld = min(max(cs[CS_W_I] / max(cp[CP_IF_I], 1e-9), -0.9), 0.9)
    ld = math.asin(s_ld)
    cs[CS_MODE] = MODE_IF_RAMP
    cs[CS_T_MODE] = 0.0
    cs[CS_W_IF] = we
    cs[CS_IQ_IF_F] = cs[CS_W_I]
    _rotate_current_integrators(cs, -ld)  # re-expressed in the I-f frame
    th = wrap_angle(th + ld)
    cs[CS_TH_IF] = wrap_angle(th + we * ts)
    return th, cp[CP_IF_I] + id_inj


@njit(cache=True, inline="always")
def _speed_loop(cs, cp, w_ref_m, w_m_fb, ts):
    """Speed PI -> i_q* [A], limited, integrator back-calculated."""
    w_err = w_ref_m - w_m_fb
    u = pi_output(cp[CP_KP_W], cs[CS_W_I], w_err)
    u_sat = min(max(u, -cp[CP_IMAX]), cp[CP_IMAX])
    cs[CS_W_I] = pi_update(cs[CS_W_I], cp[CP_KI_W], ts, w_err, u, u_sat)
    cs[CS_MODE] = MODE_CLOSED_LOOP
    return u_sat


@njit(cache=True, inline="always")
def _current_loops(cs, cp, ia, ib, th, we, id_ref, iq_ref, vdc, ts, out):
    """dq current PIs with decoupling, inverse Park at the advanced angle, SVPWM with the
    hexagon limit, deadtime feed-forward; writes the CO_* row."""
    c_t = math.cos(th)
    s_t = math.sin(th)
    i_d, i_q = park(ia, ib, c_t, s_t)
    lh = cp[CP_L]
    ed = id_ref - i_d
    eq = iq_ref - i_q
    dec = cp[CP_DECOUPLE]
    vd_u = pi_output(cp[CP_KP_I], cs[CS_ID_I], ed) - dec * we * lh * iq_ref
    vq_u = pi_output(cp[CP_KP_I], cs[CS_IQ_I], eq) + dec * we * (lh * id_ref + cp[CP_LAM])
    th_adv = th + cp[CP_ADV] * ts * we
    c_a = math.cos(th_adv)
    s_a = math.sin(th_adv)
    va, vb = inv_park(vd_u, vq_u, c_a, s_a)
    da, db, dc, scale = _svpwm(va, vb, vdc)
    vd_s = vd_u * scale
    vq_s = vq_u * scale
    cs[CS_ID_I] = pi_update(cs[CS_ID_I], cp[CP_KI_I], ts, ed, vd_u, vd_s)
    cs[CS_IQ_I] = pi_update(cs[CS_IQ_I], cp[CP_KI_I], ts, eq, vq_u, vq_s)
    if cp[CP_TDCOMP] > 0.0:
        # deadtime feed-forward on the reference current's sign per phase
        ra, rb = inv_park(id_ref, iq_ref, c_a, s_a)
        xa, xb, xc = inv_clarke(ra, rb)
        dd = cp[CP_TDCOMP] / ts
        da += dd * (1.0 if xa > 0.0 else -1.0)
        db += dd * (1.0 if xb > 0.0 else -1.0)
        dc += dd * (1.0 if xc > 0.0 else -1.0)
    out[CO_DA] = min(max(da, 0.0), 1.0)
    out[CO_DB] = min(max(db, 0.0), 1.0)
    out[CO_DC] = min(max(dc, 0.0), 1.0)
    out[CO_EN] = 1.0
    out[CO_ID] = i_d
    out[CO_IQ] = i_q
    out[CO_ID_REF] = id_ref
    out[CO_IQ_REF] = iq_ref
    out[CO_VD] = vd_s
    out[CO_VQ] = vq_s
    out[CO_TH] = th
    out[CO_MODE] = cs[CS_MODE]
    out[CO_FAULT] = 0.0


@njit(cache=True, inline="always")
def _emf_lock(cs, cp, fr, ia, ib, th, we, ts):
    """Loss of lock judged from the drive's own signals, whatever the observer's valid flag
    says: the back-EMF in the estimate's frame from the frame's measured line voltages
    (the average over the period just ended, so at mid-period angle) and currents,
    e_dq = v_dq - R^ i_dq - w^ L^ J i_dq, which is w lambda on the q axis while the
    estimate holds the rotor.  Two disagreements (docs/engine.md, *Protections*):
    LOCK_EMF_SPEED, the speed it implies, |e| / lambda^, above 1.5 |w^| + margin (a rotor
    running away under a frame that drifts); LOCK_EMF_ANGLE, above the margin's speed the
    back-EMF more than the set angle off the q axis of w^'s sign.  Returns the LOCK_* seen
    this period (LOCK_OK: agreement)."""
    th_m = th - 0.5 * we * ts
    c_t = math.cos(th_m)
    s_t = math.sin(th_m)
    va = (fr[FR_VAB] - fr[FR_VCA]) / 3.0
    vb = fr[FR_VBC] * 0.5773502691896258  # 1/sqrt(3)
    vd, vq = park(va, vb, c_t, s_t)
    i_d, i_q = park(ia, ib, c_t, s_t)
    wl = we * cp[CP_L]
    ed = vd - cp[CP_R] * i_d + wl * i_q
    eq = vq - cp[CP_R] * i_q - wl * i_d
    a = pole(cp[CP_LOCK_LPF], ts)
    cs[CS_EMF_D] = lowpass_step(cs[CS_EMF_D], ed, a)
    cs[CS_EMF_Q] = lowpass_step(cs[CS_EMF_Q], eq, a)
    cs[CS_EMF_MAG] = lowpass_step(cs[CS_EMF_MAG], math.sqrt(ed * ed + eq * eq), a)
    lam = cp[CP_LAM]
    margin = cp[CP_LOCK_MARGIN]
    if cs[CS_EMF_MAG] > (1.5 * abs(we) + margin) * lam:
        return LOCK_EMF_SPEED
    mag = math.sqrt(cs[CS_EMF_D] ** 2 + cs[CS_EMF_Q] ** 2)
    if mag > margin * lam:
        along = cs[CS_EMF_Q] if we >= 0.0 else -cs[CS_EMF_Q]
        if along < cp[CP_LOCK_COS] * mag:
            return LOCK_EMF_ANGLE
    return LOCK_OK


@njit(cache=True, inline="always")
def _references(cs, cp, fr, est, w_ref_m, id_inj, out):
    """Everything a control period does before the current loops: measure + protect ->
    position feedback -> references (align / I-f / closed loop).  Returns (run, i_alpha,
    i_beta, theta, w_e, i_d*, i_q*); run False: tripped, the PWM-off row is written."""
    ts = cp[CP_TS]
    p = cp[CP_P]
    cs[CS_T_MODE] += ts
    out[CO_W_REF] = w_ref_m
    ia, ib = clarke(fr[FR_IA], fr[FR_IB], fr[FR_IC])
    if _protect(cs, cp, fr, out, ia, ib, ts):
        return False, ia, ib, 0.0, 0.0, 0.0, 0.0
    th_enc, w_enc = _encoder_feedback(cs, cp, fr, p, ts)
    # ---------------------------------------------------------------- position feedback
    mode = cs[CS_MODE]
    if cp[CP_SRC] == SRC_ENCODER:
        mode = MODE_CLOSED_LOOP
        th = th_enc
        we = w_enc
    else:
        th = est[ES_TH]
        we = est[ES_W]
        if not math.isfinite(th) or not math.isfinite(we):
            _trip(cs, out, FAULT_POSITION_INVALID)
            return False, ia, ib, 0.0, 0.0, 0.0, 0.0
        if mode == MODE_CLOSED_LOOP:
            if est[ES_VALID] == 0.0:
                cs[CS_INV_T] += ts
                if cs[CS_INV_T] > cp[CP_INV_TIMEOUT]:
                    # PLL error or flux magnitude out of bounds for too long
                    cs[CS_LOCK_WHY] = LOCK_INVALID
                    _trip(cs, out, FAULT_LOSS_OF_LOCK)
                    return False, ia, ib, 0.0, 0.0, 0.0, 0.0
            else:
                cs[CS_INV_T] = 0.0
            if cp[CP_LOCK_MARGIN] > 0.0:
                # the observer's own flag is not trusted alone (a user's plugin may lie)
                why = _emf_lock(cs, cp, fr, ia, ib, th, we, ts)
                if why == LOCK_OK:
                    cs[CS_LOCK_T] = 0.0
                else:
                    cs[CS_LOCK_T] += ts
                    cs[CS_LOCK_WHY] = why
                    if cs[CS_LOCK_T] > cp[CP_LOCK_TIMEOUT]:
                        _trip(cs, out, FAULT_LOSS_OF_LOCK)
                        return False, ia, ib, 0.0, 0.0, 0.0, 0.0
    w_m_fb = we / p
    # an estimate's speed is a measurement once the drive rides it (closed loop) or the
    # observer holds the rotor: before that (align, I-f, a restart after PWM off with the
    # flux near 0) an invalid estimate's PLL wanders with the sensor noise -- 3 000-5 000 rpm
    # with the rotor at 60 rpm -- and is no speed to trip on
    speed_measured = cp[CP_SRC] == SRC_ENCODER or mode == MODE_CLOSED_LOOP or est[ES_VALID] != 0.0
    if speed_measured and abs(w_m_fb) > cp[CP_OS_TRIP]:
        _trip(cs, out, FAULT_OVERSPEED)
        return False, ia, ib, 0.0, 0.0, 0.0, 0.0
    cs[CS_WFB_F] = lowpass_step(cs[CS_WFB_F], w_m_fb, pole(cp[CP_WFB_LPF], ts))
    # ---------------------------------------------------------------- references
    iq_ref = 0.0
    id_ref = id_inj
    if mode == MODE_ALIGN:
        th = 0.0
        we = 0.0
        id_ref = _align(cs, cp)
    elif mode == MODE_IF_RAMP:
        th, we, id_ref, mode = _if_ramp(cs, cp, est, w_ref_m, id_inj, ia, ib, p, ts)
        if mode == MODE_FAULT:
            _trip(cs, out, FAULT_START_FAILED)
            return False, ia, ib, 0.0, 0.0, 0.0, 0.0
    if mode == MODE_CLOSED_LOOP:
        if (
            cp[CP_SRC] == SRC_ESTIMATE
            and abs(w_ref_m) < cp[CP_HANDBACK]
            and cs[CS_MODE] == MODE_CLOSED_LOOP
            and cs[CS_T_MODE] > 0.05
        ):
            th, id_ref = _hand_back(cs, cp, th, we, id_inj, ts)
            iq_ref = 0.0
        else:
            iq_ref = _speed_loop(cs, cp, w_ref_m, w_m_fb, ts)
    out[CO_W_FB] = w_m_fb
    return True, ia, ib, th, we, id_ref, iq_ref


@njit(cache=True)
def controller_step(cs, cp, fr, est, w_ref_m, id_inj, out):
    """One control period.  `est` is the driving observer's ES_* row (ignored in encoder
    mode); `w_ref_m` the mechanical speed reference [rad/s]; `id_inj` an additive i_d*
    injection [A] (frequency-response sweeps).  Writes CO_* into `out`.
    measure + protect -> position feedback -> references (align / I-f / closed loop) ->
    current loops."""
    run, ia, ib, th, we, id_ref, iq_ref = _references(cs, cp, fr, est, w_ref_m, id_inj, out)
    if run:
        _current_loops(cs, cp, ia, ib, th, we, id_ref, iq_ref, fr[FR_VDC], cp[CP_TS], out)


# ====================================================================== split mode
# The host runs `host_reference_step` on every (decimated) sample j at D*Ts: everything
# `controller_step` does except the current loops.  Its answer (RF_*) reaches the drive,
# which takes it at a PWM period boundary (`split_drive_take_reference`) and then runs
# `split_drive_step` every period at Ts: the current loops on the angle extrapolated from
# the reference, theta_k = theta_j + omega_j (t_k - t_j).  The C firmware core implements
# the same two drive-side functions.


@njit(cache=True)
def host_reference_step(cs, cp, fr, est, w_ref_m, id_inj, out, ref):
    """The host's half of split mode, one sample (`cp` with CP_TS = D*Ts: the host's sample
    period).  Writes the reference row `ref` (RF_*) and the host's part of the CO_* row:
    references, measured dq current at the angle used, angle, mode, fault, speeds; duties
    and voltages belong to the drive (0.5 and 0 here)."""
    run, ia, ib, th, we, id_ref, iq_ref = _references(cs, cp, fr, est, w_ref_m, id_inj, out)
    if run:
        i_d, i_q = park(ia, ib, math.cos(th), math.sin(th))
        out[CO_DA] = 0.5
        out[CO_DB] = 0.5
        out[CO_DC] = 0.5
        out[CO_EN] = 1.0
        out[CO_ID] = i_d
        out[CO_IQ] = i_q
        out[CO_ID_REF] = id_ref
        out[CO_IQ_REF] = iq_ref
        out[CO_VD] = 0.0
        out[CO_VQ] = 0.0
        out[CO_TH] = th
        out[CO_MODE] = cs[CS_MODE]
        out[CO_FAULT] = 0.0
    ref[RF_ID_REF] = out[CO_ID_REF]
    ref[RF_IQ_REF] = out[CO_IQ_REF]
    ref[RF_TH] = wrap_angle(th) if run else 0.0
    ref[RF_W] = we if run else 0.0
    ref[RF_EN] = out[CO_EN]
    ref[RF_MODE] = out[CO_MODE]
    ref[RF_FAULT] = out[CO_FAULT]


@njit(cache=True)
def split_drive_reset(cs, dr):
    """The drive side before its first reference: no reference, PWM off, no fault."""
    controller_reset(cs)
    for j in range(DR_N):
        dr[j] = 0.0


@njit(cache=True)
def split_drive_take_reference(cs, dr, ref, since_sample_s):
    """The drive takes a new reference at a PWM period boundary; `since_sample_s` is the
    time from the reference's sample instant t_j to this boundary's sample instant
    (lockstep: D*Ts, the same timing as a duty in host mode; a late reference: more).  The
    current integrators are rotated from the old extrapolated frame to the new one at this
    instant (what the handover does in `_if_ramp`); with PWM off they restart from zero."""
    th_new = ref[RF_TH] + ref[RF_W] * since_sample_s
    if ref[RF_EN] > 0.5 and dr[DR_HAVE] > 0.5 and dr[DR_EN] > 0.5:
        th_old = dr[DR_TH] + dr[DR_W] * dr[DR_DT]
        _rotate_current_integrators(cs, wrap_angle(th_old - th_new))
    else:
        cs[CS_ID_I] = 0.0
        cs[CS_IQ_I] = 0.0
    dr[DR_ID_REF] = ref[RF_ID_REF]
    dr[DR_IQ_REF] = ref[RF_IQ_REF]
    dr[DR_TH] = ref[RF_TH]
    dr[DR_W] = ref[RF_W]
    dr[DR_EN] = ref[RF_EN]
    dr[DR_MODE] = ref[RF_MODE]
    dr[DR_FAULT] = ref[RF_FAULT]
    dr[DR_DT] = since_sample_s
    dr[DR_AGE] = 0.0
    dr[DR_HAVE] = 1.0


@njit(cache=True)
def split_drive_step(cs, cp, dr, fr, out):
    """The drive's half of split mode, one PWM period at Ts (`cp`: the drive's parameters,
    CP_TS = Ts): the drive's protections (bad sample, over-current, I2t, bus voltage), the
    reference timeout (no new reference for CP_REF_TIMEOUT with PWM on: PWM off, WATCHDOG
    latched), then `_current_loops` on theta_j + omega_j (t_k - t_j) with the references
    limited to +-CP_IMAX.  Writes the CO_* row (the speeds are the host's: left as they are)."""
    ts = cp[CP_TS]
    ia, ib = clarke(fr[FR_IA], fr[FR_IB], fr[FR_IC])
    if _protect(cs, cp, fr, out, ia, ib, ts):
        return
    if dr[DR_HAVE] < 0.5 or dr[DR_EN] < 0.5:
        # no reference yet, or the host switched the PWM off (its fault, if any, recorded)
        i_d, i_q = park(ia, ib, math.cos(dr[DR_TH]), math.sin(dr[DR_TH]))
        out[CO_DA] = 0.5
        out[CO_DB] = 0.5
        out[CO_DC] = 0.5
        out[CO_EN] = 0.0
        out[CO_ID] = i_d
        out[CO_IQ] = i_q
        out[CO_ID_REF] = 0.0
        out[CO_IQ_REF] = 0.0
        out[CO_VD] = 0.0
        out[CO_VQ] = 0.0
        out[CO_TH] = dr[DR_TH]
        out[CO_MODE] = dr[DR_MODE] if dr[DR_HAVE] > 0.5 else MODE_DISABLED
        out[CO_FAULT] = dr[DR_FAULT]
        dr[DR_DT] += ts
        dr[DR_AGE] += ts
        return
    if cp[CP_REF_TIMEOUT] > 0.0 and dr[DR_AGE] > cp[CP_REF_TIMEOUT] * (1.0 + 1e-9):
        _trip(cs, out, FAULT_WATCHDOG)
        return
    lim = cp[CP_IMAX]
    id_ref = min(max(dr[DR_ID_REF], -lim), lim)
    iq_ref = min(max(dr[DR_IQ_REF], -lim), lim)
    th = wrap_angle(dr[DR_TH] + dr[DR_W] * dr[DR_DT])
    _current_loops(cs, cp, ia, ib, th, dr[DR_W], id_ref, iq_ref, fr[FR_VDC], ts, out)
    out[CO_MODE] = dr[DR_MODE]
    dr[DR_DT] += ts
    dr[DR_AGE] += ts


def host_params(cp: np.ndarray, decimation: int) -> np.ndarray:
    """The host's parameter row in split mode: the controller's, stepping at decimation x Ts
    (speed loop, start-up, protections on the decimated samples; the current gains stay the
    PWM-rate design the drive runs)."""
    out = cp.copy()
    out[CP_TS] = cp[CP_TS] * int(decimation)
    return out
