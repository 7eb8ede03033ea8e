"""Field-oriented control: dq current PI loops, speed PI, SVPWM, sensorless start-up.

Per PWM period (frame k in, duty out; the duty is applied over [t_{k+1}, t_{k+2}]):
  measure   Clarke/Park of the sampled currents at the position source's angle
  feedback  speed PI -> i_q*, current PIs with cross-coupling and back-EMF feed-forward
  output    inverse Park at theta + 1.5 Ts w (the voltage acts on average 1.5 periods
            later), SVPWM (min-max zero sequence) with the hexagon limit
  update    integrators back-calculated from the realised (limited) voltage.

Loop design (`design_current_loop`): the textbook law K_p = L w_cc, K_i = R w_cc cancels the
RL pole; with the 1.5-period delay of a real digital drive the closed loop then peaks and its
-3 dB bandwidth overshoots the target.  So the gain is scaled until the *discrete* closed
loop (ZOH RL plant, one period of computation delay, the PI) has exactly the requested
-3 dB bandwidth.  The speed PI is designed the same way on J s + B with the current loop
approximated as its designed first-order bandwidth.

Start-up without a position sensor (`position_source` = estimate): align (d-current at a
fixed angle), then an open-loop I-f ramp (current vector of fixed magnitude ON an angle
integrated from a ramped speed; the rotor follows at a load angle), handover to the observer
above `handover_speed` once its estimate is valid, and back to I-f below `handback_speed`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from fluxdrive.core.blocks import lowpass_step, pi_output, pi_update, pll_gains, pll_step, pole
from fluxdrive.core.layout import Layout
from fluxdrive.core.machine import (
    ConfigError,
    MachineCard,
    card_current_bandwidth_hz,
    required,
)
from fluxdrive.core.transforms import TWO_PI, clarke, inv_clarke, inv_park, park, wrap_angle
from fluxdrive.drive.observers import ES_TH, ES_VALID, ES_W
from fluxdrive.drive.plant import FR_ENC, FR_IA, FR_IB, FR_IC, FR_VDC

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
CS_N = _CS.close(globals())

MODE_DISABLED, MODE_ALIGN, MODE_IF_RAMP, MODE_CLOSED_LOOP, MODE_FAULT = range(5)
MODE_NAMES = {0: "disabled", 1: "align", 2: "if_ramp", 3: "closed_loop", 4: "fault"}
# fault codes: the same numbers as flux_drive_msgs/msg/DriveFault
(
    FAULT_NONE,
    FAULT_OVERCURRENT,
    FAULT_OVERCURRENT_I2T,
    FAULT_OVERVOLTAGE,
    FAULT_UNDERVOLTAGE,
    FAULT_OVERSPEED,
    FAULT_LOSS_OF_LOCK,
    FAULT_POSITION_INVALID,
    FAULT_STALE_INPUT,
    FAULT_WATCHDOG,
    FAULT_BAD_SAMPLE,
    FAULT_START_FAILED,
) = range(12)
FAULT_NAMES = {
    0: "none",
    1: "over-current (instantaneous)",
    2: "over-current (I2t)",
    3: "DC-bus over-voltage",
    4: "DC-bus under-voltage",
    5: "over-speed",
    6: "loss of observer lock",
    7: "position estimate not finite",
    8: "stale input",
    9: "watchdog",
    10: "bad sample (NaN/inf)",
    11: "start-up failed",
}

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
                    _trip(cs, out, FAULT_LOSS_OF_LOCK)
                    return False, ia, ib, 0.0, 0.0, 0.0, 0.0
            else:
                cs[CS_INV_T] = 0.0
    w_m_fb = we / p
    if abs(w_m_fb) > cp[CP_OS_TRIP]:
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


# ====================================================================== design
def _current_loop_tf(kp: float, ki: float, r: float, lind: float, ts: float, f_hz: np.ndarray):
    """Discrete closed loop i/i* at f: ZOH RL plant, one period of computation delay,
    PI with forward-Euler integral (as implemented in controller_step)."""
    z = np.exp(1j * 2 * np.pi * f_hz * ts)
    a = math.exp(-r * ts / lind)
    b = (1 - a) / r if r > 0 else ts / lind
    plant = b / (z - a) / z  # one period of delay: duty(k) acts over [k+1, k+2]
    ctrl = kp + ki * ts / (z - 1)  # integral term uses past errors (output, then update)
    loop = ctrl * plant
    return loop / (1 + loop)


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


def host_params(cp: np.ndarray, decimation: int) -> np.ndarray:
    """The host's parameter row in split mode: the controller's, stepping at decimation x Ts
    (speed loop, start-up, protections on the decimated samples; the current gains stay the
    PWM-rate design the drive runs)."""
    out = cp.copy()
    out[CP_TS] = cp[CP_TS] * int(decimation)
    return out


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


# ====================================================================== trips, explained
_FRAME_FIELDS = (
    "i_a",
    "i_b",
    "i_c",
    "v_ab",
    "v_bc",
    "v_ca",
    "v_dc",
    "d_a",
    "d_b",
    "d_c",
    "enable",
    "encoder",
    "seq",
    "flags",
)


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
        return (
            f"estimate flagged invalid (PLL error or |flux| out of bounds) for more than "
            f"{cp[CP_INV_TIMEOUT]:g} s in closed loop (control.invalid_timeout_s)"
        )
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
            f"{_FRAME_FIELDS[j]} = {frame[j]}"
            for j in (FR_IA, FR_IB, FR_IC, FR_VDC, FR_ENC)
            if not math.isfinite(frame[j])
        ]
        return ", ".join(bad) or "a value not finite"
    return "latched by the controller"


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
