"""Loss of lock judged from the drive's own signals, not from the observer's valid flag: a
user's observer that lies (valid always 1, its speed held at half the truth, its angle
drifting away) makes the speed loop push full torque, and the motor would run away under
a drive that trusted it -- the over-speed trip reads the same lying speed, so it never
fires.  The back-EMF check (the frame's measured voltages and currents in the estimate's
frame: e = v - R^ i - w^ L^ J i, whose magnitude implies the speed |e| / lambda^) trips
with its reason long before 1.1x rated speed, and never on the shipped honest cases."""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from fluxdrive.analysis.metrics import trip_info
from fluxdrive.drive.control import CO_FAULT, FAULT_LOSS_OF_LOCK
from fluxdrive.drive.observers import ES_N, ES_TH, ES_VALID, ES_W, Observer
from fluxdrive.drive.plant import TR_WM
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
from fluxdrive.drive.sim import run_scenario

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "my_observer"
SCENARIO = CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml"
LIE_FROM_S = 3.0  # after the sensorless start and the load ramp: the drive is in closed loop


class LyingObserver(Observer):
    """The example flux observer (examples/my_observer: honest, it drives this case), whose
    output lies from LIE_FROM_S on: valid always, its speed held at half the speed of that
    instant (the speed loop then asks for ever more torque), its angle drifting ahead at
    20 deg/s."""

    name = "liar"

    def __init__(self, card):
        sys.path.insert(0, str(EXAMPLE))
        from my_observer.flux_pll import FluxPllObserver

        self.honest = FluxPllObserver(card)
        self.ts = card.ts_s
        self.reset()

    def reset(self):
        self.honest.reset()
        self.k = 0
        self.w_held: float | None = None

    def step(self, fr):
        out = np.array(self.honest.step(fr), dtype=float)
        assert out.shape == (ES_N,)
        t = self.k * self.ts
        self.k += 1
        if t >= LIE_FROM_S:
            if self.w_held is None:
                self.w_held = 0.5 * out[ES_W]
            out[ES_W] = self.w_held
            out[ES_TH] += math.radians(20.0) * (t - LIE_FROM_S)
            out[ES_VALID] = 1.0
        return out


@pytest.fixture
def liar_importable(monkeypatch):
    here = str(Path(__file__).resolve().parent)
    monkeypatch.syspath_prepend(here)
    monkeypatch.setenv("PYTHONPATH", f"{here}:{os.environ.get('PYTHONPATH', '')}")


def _run(margin_pu: float, duration_s: float):
    over = {
        "observers": {"liar": {"variant": "test_loss_of_lock:LyingObserver"}},
        "driving": "liar",
        "duration_s": duration_s,
        "steady_window_s": [0.5 * duration_s, duration_s],
        # the scenario's own control block with the check's margin (an override replaces it)
        "control": {
            **yaml.safe_load(SCENARIO.read_text())["control"],
            "lock_emf_margin_pu": margin_pu,
        },
    }
    sc = load_scenario(SCENARIO, overrides=over)
    return sc, run_scenario(sc, progress=False)


def test_a_lying_observer_trips_on_the_back_emf_before_1p1_rated(liar_importable):
    sc, res = _run(0.25, 6.0)
    rated = sc.machine.rated_speed_rad_s
    info = trip_info(res)
    assert info is not None, "the lying observer was trusted"
    assert info["code"] == FAULT_LOSS_OF_LOCK, info
    k = info["k"]
    assert info["t_s"] > LIE_FROM_S
    top = float(np.max(np.abs(res.truth[: k + 1, TR_WM])))
    print(f"tripped at {info['t_s']:.3f} s at {top / rated:.3f} pu: {info['message']}")
    assert top < 1.1 * rated
    # the 0.25 pu margin over 1.5 x the lying (half) speed, plus the check's 0.1 s
    assert top < 0.5 * rated
    assert "back-EMF implies" in info["message"] and "lock_emf_margin_pu" in info["message"]
    assert (res.ctrl[k:, CO_FAULT] == FAULT_LOSS_OF_LOCK).all()  # latched, PWM off


def test_without_the_check_the_same_liar_runs_the_motor_away(liar_importable):
    """The control: with the back-EMF check off (lock_emf_margin_pu 0), nothing stops the
    motor before it passes the speed at which the check tripped -- the valid flag and the
    over-speed trip both read the liar."""
    sc, res = _run(0.0, 5.0)
    rated = sc.machine.rated_speed_rad_s
    info = trip_info(res)
    top = float(np.max(np.abs(res.truth[:, TR_WM])))
    assert info is None or info["code"] != FAULT_LOSS_OF_LOCK
    assert top > 0.5 * rated, top / rated
