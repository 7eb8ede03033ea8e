"""Physics of the drive engine: numbers that follow from the equations (docs/engine.md)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fluxdrive.analysis.freqresp import analyse
from fluxdrive.analysis.metrics import compute, wrap
from fluxdrive.core.blocks import rng_new
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.control import (
    CO_ID,
    CO_ID_REF,
    CO_IQ,
    CO_VQ,
)
from fluxdrive.drive.observers import ES_LA, ES_LB, ES_TH, KernelObserver, observer_config
from fluxdrive.drive.plant import (
    FR_N,
    FR_VAB,
    FR_VBC,
    FR_VCA,
    PS_IA,
    PS_IB,
    TR_N,
    TR_THETA_E,
    TR_WM,
    machine_params,
    plant_advance,
    plant_state,
)
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
from fluxdrive.drive.sim import run_scenario
from helpers_engine import ideal_machine, make_scenario

RPM = 2 * math.pi / 60


def test_steady_state_q_voltage_matches_rs_iq_plus_emf(tmp_path):
    """Encoder drive at 300 rpm under load, ideal inverter: v_q = R i_q + w_e lambda."""
    card = ideal_machine(deadtime_s=0.0)
    sc = make_scenario(
        tmp_path,
        card,
        duration_s=1.2,
        speed_rpm=300.0,
        load_type="active",
        load_pu=[[0.0, 0.0], [0.2, 0.0], [0.4, 0.8]],
        steady_window_s=[0.9, 1.2],
    )
    r = run_scenario(sc, progress=False)
    sl = slice(9000, 12000)
    iq = r.ctrl[sl, CO_IQ].mean()
    we = r.truth[sl, TR_WM].mean() * card.pole_pairs
    expected = card.resistance_ohm * iq + we * card.flux_linkage_vs
    vq = r.ctrl[sl, CO_VQ].mean()
    assert iq == pytest.approx(0.8 * card.rated_current_a, rel=0.03)
    assert vq == pytest.approx(expected, rel=0.02), (vq, expected)


def test_deadtime_volt_second_loss_per_leg():
    """Average leg-voltage loss over a period is sign(i) Vdc td/Ts (within 2 %)."""
    card = dataclasses.replace(
        MachineCard(), capture_bits=24, dc_bus_adc_bits=24, current_noise_a=0.0, inertia_kgm2=1e3
    )
    mp = machine_params(card)
    vdt = card.dc_bus_v * card.deadtime_s / card.ts_s  # 1.44 V
    for ia_sign in (+1.0, -1.0):
        st = plant_state()
        st[PS_IA] = 6.0 * ia_sign  # i_a = 6, i_b = i_c = -3 (times the sign)
        st[PS_IB] = 0.0
        frame = np.zeros(FR_N)
        truth = np.zeros(TR_N)
        duty = np.array([0.5, 0.5, 0.5])
        plant_advance(
            st,
            mp,
            rng_new(0),
            duty,
            True,
            np.array([0.0]),
            np.array([0.0]),
            np.array([0.0, 0.0]),
            frame,
            truth,
        )
        # legs: a loses sign(i_a) vdt, b and c lose sign(i_b) vdt = -sign(i_a) vdt
        assert frame[FR_VAB] == pytest.approx(-2.0 * vdt * ia_sign, rel=0.02)
        assert frame[FR_VBC] == pytest.approx(0.0, abs=0.02 * vdt)
        assert frame[FR_VCA] == pytest.approx(2.0 * vdt * ia_sign, rel=0.02)


def test_paper_observer_tracks_60rpm_under_half_degree_with_ideal_sensors(tmp_path):
    """Ideal sensors, no deadtime, encoder drive at 60 rpm with half load ramped in."""
    card = ideal_machine(deadtime_s=0.0)
    sc = make_scenario(
        tmp_path,
        card,
        duration_s=3.0,
        speed_rpm=60.0,
        load_type="active",
        load_pu=[[0.0, 0.0], [0.5, 0.0], [1.5, 0.5]],
        steady_window_s=[2.2, 3.0],
        observers={"flux": {"variant": "paper"}},
    )
    m = compute(run_scenario(sc, progress=False))
    assert m["observers"]["flux"]["theta_err_rms_deg"] < 0.5
    assert abs(m["speed"]["mean_error_rpm"]) < 0.5


def test_phase_b_offset_pure_integrator_drifts_paper_observer_bounded(tmp_path):
    """Fig. 3: a 5 % offset on phase B makes the pure integrator drift; the LPF +
    inverse-HPF observer stays bounded (paper_robust: the literal `paper`, compensating at
    the PLL's own w^, can be kicked through w^ = 0 into a 180 deg false lock -- see the
    paper_robust experiment).  (Rig with 100x inertia: with the default
    J the offset's fundamental torque ripple swings the speed by ~100 rpm at 60 rpm, which
    would test the speed loop, not the estimator.)"""
    card = dataclasses.replace(MachineCard(), inertia_kgm2=1.5e-2)
    sc = make_scenario(
        tmp_path,
        card,
        duration_s=2.0,
        speed_rpm=60.0,
        steady_window_s=[1.0, 2.0],
        faults={"current_offset_pu": [0.0, 0.05, 0.0]},
        observers={"pure": {"variant": "pure_integrator"}, "paper": {"variant": "paper_robust"}},
    )
    r = run_scenario(sc, progress=False)
    lam = sc.machine.flux_linkage_vs
    pure = r.estimate("pure")
    centre_early = np.hypot(*pure[2000:4500, ES_LA : ES_LB + 1].mean(axis=0))
    centre_late = np.hypot(*pure[17500:20000, ES_LA : ES_LB + 1].mean(axis=0))
    assert centre_late > centre_early + 2 * lam  # the locus centre runs away
    m = compute(r)
    # bounded: the offset leaves a 1st-order error of about asin(w_c R di / (w lambda w_c))
    assert m["observers"]["paper"]["theta_err_peak_deg"] < 30.0
    paper = r.estimate("paper")
    assert np.hypot(paper[10000:, ES_LA], paper[10000:, ES_LB]).max() < 1.5 * lam


@pytest.mark.parametrize("ideal, tol", [(True, 0.02), (False, 0.15)])
def test_current_loop_bandwidth_matches_1khz_design(tmp_path, ideal, tol):
    """Encoder drive at 10 % speed, sine sweep on i_d* (20 % rated): the measured -3 dB
    bandwidth is the designed 1 kHz; with an ideal inverter within 2 %, with the 2 us
    deadtime at rated load within 15 % (at light load the deadtime's +-Vdc td/Ts acts as an
    extra small-signal resistance and lowers it further)."""
    card = ideal_machine(deadtime_s=0.0) if ideal else None
    sc = make_scenario(
        tmp_path,
        card,
        duration_s=1.0,
        speed_rpm=300.0,
        load_type="active",
        load_pu=0.0 if ideal else 1.0,
        steady_window_s=[0.5, 1.0],
        id_injection={
            "frequencies_hz": [50.0, 300.0, 600.0, 800.0, 900.0, 1000.0, 1100.0, 1250.0, 1500.0],
            "amplitude": 0.2,
            "start_s": 0.3,
            "cycles": 10,
        },
    )
    r = run_scenario(sc, progress=False)
    fr = analyse(r.ctrl[:, CO_ID], r.ctrl[:, CO_ID_REF], r.segments["current_d"], sc.machine.ts_s)
    assert fr["bandwidth_hz"] == pytest.approx(1000.0, rel=tol), fr


def test_timing_convention_voltage_pairs_with_the_current_step(tmp_path):
    """Frame k's voltage drove i(k-1) -> i(k).  Pairing it one sample late gives a
    speed-dependent angle error of about w_e Ts; the observer's pairing gives none."""
    card = ideal_machine(deadtime_s=0.0)
    sc = make_scenario(
        tmp_path,
        card,
        duration_s=1.2,
        speed_rpm=300.0,
        load_pu=0.5,
        steady_window_s=[0.8, 1.2],
        observers={"flux": {"variant": "paper"}},
    )
    r = run_scenario(sc, progress=False)
    th = r.truth[:, TR_THETA_E]
    frames = r.frames.copy()
    late = frames.copy()
    late[1:, FR_VAB : FR_VCA + 1] = frames[:-1, FR_VAB : FR_VCA + 1]  # off by one
    errs = []
    for fr in (frames, late):
        obs = KernelObserver(observer_config("paper"), card)
        est = obs.run(fr)
        errs.append(np.degrees(np.mean(wrap(est[8000:, ES_TH] - th[8000:]))))
    we_ts_deg = math.degrees(300 * RPM * card.pole_pairs * card.ts_s)  # 0.72 deg
    assert abs(errs[0]) < 0.1 * we_ts_deg
    assert abs(errs[1]) > 0.5 * we_ts_deg


def test_runs_are_repeatable_and_seeded(tmp_path):
    sc = make_scenario(
        tmp_path,
        duration_s=0.2,
        speed_rpm=60.0,
        steady_window_s=[0.1, 0.2],
        seed=7,
        observers={"flux": {"variant": "paper"}},
    )
    a = run_scenario(sc, progress=False)
    b = run_scenario(sc, progress=False)
    assert np.array_equal(a.frames, b.frames) and np.array_equal(a.est, b.est)
    sc.seed = 8
    c = run_scenario(sc, progress=False)
    assert not np.array_equal(a.frames, c.frames)


def test_paper_2pct_150load_shows_fig14_ordering():
    """The paper's case, sensorless on the flux observer (paper_robust) with measured
    voltages: stable; flux beats EMF on theta RMS with measured voltages (with commanded
    ones the deadtime 6th order dominates both, and the EMF path's lower-bandwidth PLL
    filters it more); measured voltages remove most of the 6th harmonic that uncompensated
    commanded voltages put into theta.  On the ideal bench: on the scenario's non-ideal bench
    the EMF observer on measured voltages edges out the flux one at this point (2.3 vs
    2.7 deg, docs/engine.md "Non-ideal bench")."""
    sc = load_scenario(
        CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml", overrides={"bench": {}}
    )
    m = compute(run_scenario(sc, progress=False))
    o = m["observers"]
    assert m["stable"] and m["driving"] == "flux_measured"
    assert abs(m["speed"]["mean_rpm"] - 60.0) < 1.0
    assert m["currents"]["i_q_mean_a"] == pytest.approx(1.5 * sc.machine.rated_current_a, rel=0.05)
    assert o["flux_measured"]["theta_err_rms_deg"] < o["emf_measured"]["theta_err_rms_deg"]
    for kind in ("flux", "emf"):
        h6_cmd = o[f"{kind}_commanded"]["theta_err_h6_deg"]
        h6_meas = o[f"{kind}_measured"]["theta_err_h6_deg"]
        assert h6_cmd > 5.0
        assert h6_meas < 0.1 * h6_cmd
