"""The I-f -> observer handover criterion (control.handover_agree_lpf_hz) against an estimate
that follows a rotor swinging about the I-f vector, as an unloaded rotor does (undamped,
sqrt(p K_t I_if / J)/2 pi = 23 Hz on the default card at 0.6 pu): the per-sample check is
reset by every swing beyond the 30 % speed band and never hands over; the low-passed check
sees the swing's mean (the ramp's speed and angle) and hands over one dwell after the ramp
reaches the handover speed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.control import (
    CO_MODE,
    CO_N,
    CS_N,
    CS_TH_IF,
    CS_W_IF,
    MODE_CLOSED_LOOP,
    ControllerConfig,
    controller_reset,
    controller_step,
)
from fluxdrive.drive.observers import ES_N, ES_TH, ES_VALID, ES_W
from fluxdrive.drive.plant import FR_N, FR_VDC

CARD = MachineCard()
RPM = 2 * math.pi / 60
SWING_HZ, SWING_SPEED, SWING_ANGLE_RAD = 23.0, 0.5, math.radians(30.0)
ALIGN_S, ACCEL_RPM_S, HANDOVER_RPM, DWELL_S = 0.15, 300.0, 40.0, 0.3


def _handover_time(lpf_hz: float, t_end_s: float = 2.0) -> float | None:
    cfg = ControllerConfig(
        position_source="estimate",
        if_current_pu=0.6,
        align_time_s=ALIGN_S,
        if_accel_rpm_s=ACCEL_RPM_S,
        handover_rpm=HANDOVER_RPM,
        handback_rpm=20.0,
        handover_dwell_s=DWELL_S,
        handover_agree_lpf_hz=lpf_hz,
    )
    cp = cfg.to_params(CARD)
    cs = np.zeros(CS_N)
    controller_reset(cs)
    fr = np.zeros(FR_N)
    fr[FR_VDC] = CARD.dc_bus_v
    est = np.zeros(ES_N)
    out = np.zeros(CO_N)
    ts = CARD.ts_s
    for k in range(int(t_end_s / ts)):
        t = k * ts
        s = math.sin(2 * math.pi * SWING_HZ * t)
        # the estimate tracks a rotor that swings about the I-f vector: its speed +-50 %
        # about the ramp's, its angle +-30 deg about the vector (load angle ~0 at no load)
        est[ES_TH] = cs[CS_TH_IF] + SWING_ANGLE_RAD * math.cos(2 * math.pi * SWING_HZ * t)
        est[ES_W] = cs[CS_W_IF] * (1.0 + SWING_SPEED * s)
        est[ES_VALID] = 1.0 if t > ALIGN_S else 0.0
        controller_step(cs, cp, fr, est, 60.0 * RPM, 0.0, out)
        if out[CO_MODE] == MODE_CLOSED_LOOP:
            return t
    return None


def test_per_sample_check_is_reset_by_the_swing():
    assert _handover_time(0.0) is None


def test_filtered_check_hands_over_one_dwell_after_the_handover_speed():
    # the ramp reaches the handover speed after the alignment and HANDOVER/ACCEL; the 2 Hz
    # filter leaves 0.5/sqrt(1 + (23/2)^2) = 4 % of the speed swing, inside the 30 % band
    t_reach = ALIGN_S + HANDOVER_RPM / ACCEL_RPM_S
    t = _handover_time(2.0)
    assert t is not None
    assert t == pytest.approx(t_reach + DWELL_S, abs=0.005)
