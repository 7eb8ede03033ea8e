"""A sensorless start that cannot hand over latches "start-up failed" after
`handover_timeout_s` at the handover speed, instead of ramping open-loop for ever.

Physics: in I-f the current vector of magnitude I_if leads the rotor by the load angle
delta, and the rotor carries K_t I_if sin(delta) at most K_t I_if.  A passive brake above that
holds the rotor still while the I-f angle turns: no observer can agree with the ramp, and
the drive trips once the ramp has waited the timeout at the handover speed.  Below it the
rotor follows the ramp and the drive hands over.  (In-process, ideal bench.)"""

from __future__ import annotations

import numpy as np
import pytest
from fluxdrive.analysis.metrics import trip_info
from fluxdrive.drive.control import CO_FAULT, CO_MODE, FAULT_START_FAILED, MODE_CLOSED_LOOP
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.drive.sim import run_scenario

IF_PU, TIMEOUT_S, ALIGN_S = 0.6, 1.0, 0.15


def _run(load_pu: float):
    over = {
        "bench": {},
        "duration_s": 1.8,
        "load_type": "brake",
        "load_pu": [[0.0, load_pu], [10.0, load_pu]],
        "steady_window_s": [1.5, 1.8],
        "control": {
            "if_current_pu": IF_PU,
            "if_accel_pu_s": 0.1,
            "handover_pu": 0.0133333333333,
            "handback_pu": 0.00666666666667,
            "align_time_s": ALIGN_S,
            "handover_timeout_s": TIMEOUT_S,
        },
    }
    sc = load_scenario(scenario_path("paper_2pct_150load.yaml"), overrides=over)
    return run_scenario(sc, progress=False)


def test_brake_above_the_if_torque_latches_start_up_failed():
    res = _run(1.0)
    fault = res.ctrl[:, CO_FAULT]
    k = int(np.argmax(fault != 0))
    assert fault[k] == FAULT_START_FAILED
    # the ramp reaches the 40 rpm handover speed at 300 rpm/s after the alignment, then waits
    t_hand = ALIGN_S + 40.0 / 300.0
    assert res.t[k] == pytest.approx(t_hand + TIMEOUT_S, abs=2e-3)
    rep = trip_info(res)
    assert "start-up failed: no handover after 1 s" in rep["message"]
    assert "if_current_pu" in rep["message"]


def test_brake_below_the_if_torque_hands_over():
    res = _run(0.45)  # K_t I_if sin(delta) = 0.45 pu at delta = 49 deg
    assert not np.any(res.ctrl[:, CO_FAULT] != 0)
    assert np.any(res.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP)
