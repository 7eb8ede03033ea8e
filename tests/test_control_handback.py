"""Sensorless hand-back (closed loop -> I-f below handback_rpm) for either sign of speed and
torque: the I-f vector takes over the torque the closed loop carried (reversal)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.analysis.metrics import RAD_S_TO_RPM, wrap
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.control import (
    CO_ID_REF,
    CO_IQ_REF,
    CO_MODE,
    CO_N,
    CO_TH,
    CS_MODE,
    CS_N,
    CS_T_MODE,
    CS_W_I,
    CS_W_IF,
    MODE_CLOSED_LOOP,
    MODE_IF_RAMP,
    ControllerConfig,
    controller_reset,
    controller_step,
)
from fluxdrive.drive.observers import ES_N, ES_TH, ES_VALID, ES_W
from fluxdrive.drive.plant import FR_N, FR_VDC, TR_THETA_E, TR_WM

CARD = MachineCard()
RPM = 2 * math.pi / 60


@pytest.mark.parametrize(
    "speed_rpm, iq_pu", [(30.0, 0.4), (-30.0, -0.4), (-30.0, 0.4), (30.0, -0.4), (30.0, 1.5)]
)
def test_handback_keeps_the_torque_current_for_either_sign(speed_rpm, iq_pu):
    """At hand-back the I-f vector sits at theta^ + asin(i_q/I_if): its q-component in the
    estimated rotor frame is the torque current the speed loop was holding (clipped at
    sin = 0.9 when the I-f current cannot carry it); the ramp starts at the estimated speed."""
    cfg = ControllerConfig(
        position_source="estimate",
        if_current_pu=1.0,
        handback_rpm=20.0,
        handover_rpm=40.0,
        speed_observer_pll_hz=25.0,
    )
    cp = cfg.to_params(CARD)
    cs = np.zeros(CS_N)
    controller_reset(cs)
    i_if = CARD.rated_current_a
    iq = iq_pu * CARD.rated_current_a
    cs[CS_MODE] = MODE_CLOSED_LOOP
    cs[CS_T_MODE] = 1.0
    cs[CS_W_I] = iq
    fr = np.zeros(FR_N)
    fr[FR_VDC] = 72.0
    est = np.zeros(ES_N)
    est[ES_TH] = 1.0
    est[ES_W] = speed_rpm * RPM * CARD.pole_pairs
    est[ES_VALID] = 1.0
    out = np.zeros(CO_N)
    w_ref = math.copysign(10.0, speed_rpm) * RPM  # below handback_rpm
    controller_step(cs, cp, fr, est, w_ref, 0.0, out)
    assert out[CO_MODE] == MODE_IF_RAMP
    assert out[CO_ID_REF] == pytest.approx(i_if)
    assert out[CO_IQ_REF] == 0.0
    ld = float(wrap(np.array(out[CO_TH] - est[ES_TH])))
    assert i_if * math.sin(ld) == pytest.approx(
        float(np.clip(iq, -0.9 * i_if, 0.9 * i_if)), rel=1e-9
    )
    assert cs[CS_W_IF] == pytest.approx(est[ES_W])
    # the next period continues the ramp from that angle, in the direction of rotation
    th0 = out[CO_TH]
    controller_step(cs, cp, fr, est, w_ref, 0.0, out)
    dth = float(wrap(np.array(out[CO_TH] - th0)))
    assert math.copysign(1.0, dth) == math.copysign(1.0, speed_rpm)


def test_sensorless_reversal_under_active_load_hands_back_without_a_swing(tmp_path):
    """+60 -> -60 rpm with 0.4 pu active load torque, flux observer driving: hand-back at
    20 rpm, I-f through zero, handover again at -40 rpm.  The I-f load angle stays at
    asin(0.4/1.0) = 24 deg (no loss of synchronism) and the speed does not swing: before the
    torque-keeping hand-back the step to zero torque set off the I-f ramp's undamped
    load-angle oscillation (+-150 rpm)."""
    from fluxdrive.analysis.metrics import compute
    from fluxdrive.drive.control import CO_MODE as MODE
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive.experiments.registry import OBS4, build

    sc = build(
        name="reversal_unit",
        duration_s=7.0,
        seed=1,
        speed_rpm=[[0.0, 60.0], [3.6, 60.0], [4.8, -60.0]],
        load_type="active",
        load_pu=[[0.0, 0.0], [0.6, 0.0], [2.6, 0.4]],
        steady_window_s=[6.0, 7.0],
        driving="flux_measured",
        control={"if_current_pu": 1.0, "handover_rpm": 40.0, "handback_rpm": 20.0},
        observers={"flux_measured": OBS4["flux_measured"]},
    )
    r = run_scenario(sc, progress=False)
    m = compute(r)
    assert m["stable"] and m["speed"]["mean_rpm"] == pytest.approx(-60.0, abs=3.0)
    mode = r.ctrl[:, MODE]
    k_if = np.nonzero((mode == MODE_IF_RAMP) & (r.t > 2.0))[0]
    assert k_if.size > 0 and mode[-1] == MODE_CLOSED_LOOP
    load_angle = np.degrees(wrap(r.ctrl[k_if, CO_TH] - r.truth[k_if, TR_THETA_E]))
    assert np.max(np.abs(load_angle)) < 35.0, np.max(np.abs(load_angle))
    slip = (r.truth[k_if, TR_WM] - r.w_ref[k_if]) * RAD_S_TO_RPM
    assert np.max(np.abs(slip)) < 30.0, np.max(np.abs(slip))
