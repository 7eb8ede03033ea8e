"""The run table (sim, run, demo, replay) says which observer is lowest on which metric."""

from __future__ import annotations

from fluxdrive.analysis.metrics import RANKED, _lowest_line, lowest_by_metric


def test_the_run_table_names_the_lowest_observer_per_metric():
    """Each ranked metric's winner among observers with valid data (an observer without valid
    data, or a NaN, never wins), printed on one line of the run table."""
    keys = [k for k, _, _ in RANKED]
    obs = {
        "a": dict.fromkeys(keys, 2.0),
        "b": {**dict.fromkeys(keys, 1.0), "theta_err_peak_deg": 3.0},
        "c": {**dict.fromkeys(keys, 0.5), "valid_data": False},
        "d": dict.fromkeys(keys, float("nan")),
    }
    low = lowest_by_metric(obs)
    assert low["theta_err_rms_deg"] == {"observer": "b", "value": 1.0}
    assert low["theta_err_peak_deg"] == {"observer": "a", "value": 2.0}
    assert {v["observer"] for k, v in low.items() if k != "theta_err_peak_deg"} == {"b"}
    line = _lowest_line({"observers": obs, "lowest": low})
    assert line is not None and "θ̃ RMS b (1°)" in line and "θ̃ peak a (2°)" in line
    assert _lowest_line({"observers": {"a": obs["a"]}}) is None  # one observer: no ranking
