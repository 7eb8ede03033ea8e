"""Bad samples and sequence faults at the observer: documented policy, no corruption."""

from __future__ import annotations

import numpy as np
import pytest
from fluxdrive.analysis.metrics import wrap
from fluxdrive.core.machine import ConfigError, MachineCard
from fluxdrive.drive.control import ControllerConfig
from fluxdrive.drive.observers import ES_TH, ES_VALID, OS_BAD, OS_GAPS, OS_STALE
from fluxdrive.drive.plant import FR_IA, FR_SEQ, FR_VAB, TR_THETA_E
from fluxdrive.drive.sim import DriveSetup, run_scenario
from helpers_engine import make_scenario


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    sc = make_scenario(
        tmp_path_factory.mktemp("pol"),
        duration_s=1.2,
        speed_rpm=300.0,
        steady_window_s=[0.8, 1.2],
        observers={"flux": {"variant": "paper"}},
    )
    return sc, run_scenario(sc, progress=False)


def _replay(sc, frames):
    obs = DriveSetup(sc).kernel_observer("flux")
    out = np.array([obs.step(f) for f in frames])
    return obs, out


def _err_deg(out, truth, k0):
    return np.degrees(np.abs(wrap(out[k0:, ES_TH] - truth[k0:, TR_THETA_E])))


def test_nan_and_inf_samples_are_flagged_held_and_counted(run):
    sc, r = run
    frames = r.frames.copy()
    bad = [9000, 9001, 9500]
    frames[bad[0], FR_IA] = np.nan
    frames[bad[1], FR_IA] = np.inf
    frames[bad[2], FR_VAB] = -np.inf
    obs, out = _replay(sc, frames)
    assert all(out[k, ES_VALID] == 0.0 for k in bad)
    assert obs.state[OS_BAD] == 3
    assert np.all(np.isfinite(out))  # nothing non-finite leaks into the estimate
    assert _err_deg(out, r.truth, 10500).max() < 2.0  # recovered


def test_repeated_and_backwards_frames_are_ignored(run):
    sc, r = run
    frames = np.concatenate(
        [r.frames[:9000], r.frames[8990:9000], r.frames[8999:9000], r.frames[9000:]]
    )
    truth = np.concatenate([r.truth[:9000], r.truth[8990:9000], r.truth[8999:9000], r.truth[9000:]])
    obs, out = _replay(sc, frames)
    assert obs.state[OS_STALE] == 11
    assert np.all(out[9000:9011, ES_VALID] == 0.0)
    ref_obs, ref = _replay(sc, r.frames)
    # the stream after the duplicates is processed exactly as without them
    assert np.array_equal(out[9011:], ref[9000:])
    assert truth.shape[0] == out.shape[0]


def test_sequence_gap_coasts_and_recovers(run):
    sc, r = run
    keep = np.ones(len(r.frames), bool)
    keep[9000:9050] = False  # 5 ms of frames lost
    frames = r.frames[keep]
    truth = r.truth[keep]
    obs, out = _replay(sc, frames)
    assert obs.state[OS_GAPS] == 50
    assert out[9000, ES_VALID] == 0.0
    k_after = 9000
    assert frames[k_after, FR_SEQ] == 9050
    # the angle coasted across the gap: small error right after, back to normal soon
    assert _err_deg(out, truth, k_after)[0] < 5.0
    assert _err_deg(out, truth, k_after + 2000).max() < 1.0


def test_controller_config_rejects_bad_values_with_the_key():
    card = MachineCard()
    for kw, key in [
        ({"current_bandwidth_hz": -5.0}, "current_bandwidth_hz"),
        ({"speed_bandwidth_hz": "fast"}, "speed_bandwidth_hz"),
        ({"current_limit_pu": 9.0}, "current_limit_pu"),
        ({"current_bandwidth_hz": 4000.0}, "quarter of the PWM"),
    ]:
        with pytest.raises(ConfigError, match=key):
            ControllerConfig(**kw).to_params(card)
