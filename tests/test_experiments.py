"""Each experiment's core assertion, on its quick version (in-process, serial)."""

from __future__ import annotations

import json

import pytest
from fluxdrive.experiments import run_experiment, write_report


def _run(name, tmp_path):
    res = run_experiment(name, tmp_path, quick=True, pool=None, echo=False)
    write_report(tmp_path, {name: res})
    return res


def _holds(res, start):
    return next(c for c in res["claims"] if c["claim"].startswith(start))["holds"]


def test_fig14_measured_voltages_remove_6th_flux_has_better_snr(tmp_path):
    r = _run("fig14", tmp_path)
    assert _holds(r, "Commanded voltages: visible deadtime")
    assert _holds(r, "Measured voltages: the 6th-order")
    assert _holds(r, "Measured voltages: flux-based")
    assert _holds(r, "Sensorless flux drive")
    rep = json.loads((tmp_path / "report.json").read_text())["experiments"]["fig14"]
    assert all({"claim", "ours", "holds"} <= set(c) for c in rep["claims"])
    assert (tmp_path / "report.md").exists() and (tmp_path / "fig14_theta_error.png").exists()


def test_fig13_flux_locus_radius_and_tighter_than_emf_under_load(tmp_path):
    d = _run("fig13", tmp_path)["data"]
    assert d["no load"]["flux_mean_v"] == pytest.approx(0.59, abs=0.03)
    fl = d["full load"]
    assert fl["flux_v"][1] - fl["flux_v"][0] < fl["emf_1ms"][1] - fl["emf_1ms"][0]
    assert fl["flux_v"][1] - fl["flux_v"][0] < 0.3 * (fl["emf_raw"][1] - fl["emf_raw"][0])


def test_fig2_4_offset_drift_and_deadtime_follow_the_equations(tmp_path):
    r = _run("fig2_4", tmp_path)
    assert _holds(r, "Fig. 2 / eq. 6")
    assert _holds(r, "Fig. 3: a 5 %")
    assert _holds(r, "Fig. 4: with deadtime")
    assert _holds(r, "Fig. 4: the integration")
    assert not _holds(r, "(implied) the proposed")  # our finding at 2 % speed


def test_fig17_flux_drive_keeps_the_encoder_current_bandwidth(tmp_path):
    d = _run("fig17", tmp_path)["data"]
    enc, flux = d["encoder"]["ctrl"]["bandwidth_hz"], d["flux_measured"]["ctrl"]["bandwidth_hz"]
    assert 750 < enc < 1100
    assert flux == pytest.approx(enc, rel=0.15)


def test_fig19_light_rotor_stalls_heavier_rotor_recovers(tmp_path):
    r = _run("fig19", tmp_path)
    rows = {x["J_scale"]: x for x in r["data"]["step_vs_inertia"]}
    assert not rows[1]["stable"]
    assert rows[20]["stable"] and rows[20]["recovery_s"] < 0.25
    assert _holds(r, "Full load at 4 %")


def test_fig15_16_emf_thd_rises_at_low_speed_and_measured_voltages_cut_it(tmp_path):
    r = _run("fig15_16", tmp_path)
    assert _holds(r, "EMF THD (commanded) rises")
    assert _holds(r, "Measured voltages lower")


def test_fig18_speed_bandwidth_encoder_and_flux_10hz(tmp_path):
    """Encoder and flux drives both meet the 10 Hz speed design (the PI is designed with
    the observer's speed path).  The paper's 'EMF only 7 Hz' is a documented disagreement:
    in our model the EMF path's speed LPF costs phase margin, not bandwidth."""
    r = _run("fig18", tmp_path)
    assert _holds(r, "Encoder drive: speed bandwidth")
    assert _holds(r, "Flux-based drive: speed bandwidth")


def test_mismatch_r_is_a_magnitude_error_l_an_angle_error(tmp_path):
    r = _run("mismatch", tmp_path)
    assert _holds(r, "R^ error")
    assert _holds(r, "L^ error")
    assert _holds(r, "λ^ error")


def test_rs_adapt_recovers_a_30pct_resistance_error(tmp_path):
    r = _run("rs_adapt", tmp_path)
    rows = r["data"]["runs"]
    assert not next(x for x in rows if not x["adaptive"])["stable"]
    assert all(c["holds"] for c in r["claims"])


def test_lowest_speed_flux_measured_holds_2pct_full_load(tmp_path):
    d = _run("lowest_speed", tmp_path)["data"]["lowest"]
    assert d["flux_measured"]["lowest_rpm"] is not None and d["flux_measured"]["lowest_rpm"] <= 60


def test_graph_flag_runs_through_the_node_graph_with_the_same_numbers(tmp_path):
    """`experiment --graph`: a scenario built in memory (machine changed too) is saved to a
    file that reproduces it, run through the lockstep graph, read back from the bag, and
    gives the in-process runner's arrays and metrics exactly."""
    pytest.importorskip("rclpy")
    import numpy as np
    from fluxdrive.experiments import graph_run, sensorless
    from fluxdrive.metrics import compute
    from fluxdrive.scenario import load_scenario, save_scenario, scenario_differences
    from fluxdrive.sim import run_scenario

    sc = sensorless(120.0, 0.3, name="exp_graph", ramp_pu_s=1.0, settle_s=0.1, window_s=0.2,
                    observers={"flux_measured": {"variant": "paper"},
                               "emf_measured": {"variant": "emf"}},
                    machine_kw={"inertia_kgm2": 3.0e-4})
    p = save_scenario(sc, tmp_path / "s.yaml")
    assert scenario_differences(sc, load_scenario(p)) == []
    a = run_scenario(sc, progress=False)
    b = graph_run(sc)
    for name in ("frames", "truth", "ctrl"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for o in sc.observers:
        assert np.array_equal(a.estimate(o), b.estimate(o)), o
    ma, mb = compute(a), compute(b)
    assert ma["observers"] == mb["observers"]
    print(sc.duration_s, "s simulated; θ̃ RMS", mb["observers"]["flux_measured"]
          ["theta_err_rms_deg"])
