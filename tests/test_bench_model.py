"""The non-ideal bench (docs/engine.md, "Non-ideal bench"): each effect against its equation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fluxdrive.analysis.metrics import harmonic
from fluxdrive.core.bench import BenchConfig, Thermal, VoltageCapture, parse_bench
from fluxdrive.core.blocks import rng_new
from fluxdrive.core.machine import ConfigError, MachineCard
from fluxdrive.drive.observers import ES_LA, ES_LB, OP_L, OP_LAM, OP_R
from fluxdrive.drive.plant import (
    FR_IA,
    FR_N,
    FR_VAB,
    FR_VBC,
    FR_VDC,
    MP_TH_ON,
    PS_IA,
    PS_TW,
    TR_IA,
    TR_N,
    TR_THETA_E,
    load_config,
    machine_params,
    plant_advance,
    plant_state,
    winding_resistance,
)
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario, save_scenario
from fluxdrive.drive.sim import DriveSetup, run_scenario
from helpers_engine import ideal_machine, make_scenario

NO_LOAD = (np.array([0.0]), np.array([0.0]), load_config(0.0, 0.0))

# the paper bench's capture numbers (config/benches/paper_lab.yaml), a fine timer, no jitter
CAPTURE = VoltageCapture(
    threshold_pu=0.25,
    edge_time_s=50e-9,
    delay_rise_s=60e-9,
    delay_fall_s=25e-9,
    min_pulse_s=111e-9,
    jitter_s=0.0,
    resolution_bits=24,
)


def _run_fixed_duty(mp, duty, n, seed=1, i_alpha0=0.0):
    st = plant_state()
    st[PS_IA] = i_alpha0
    rng = rng_new(seed)
    frame = np.zeros(FR_N)
    truth = np.zeros(TR_N)
    frames = np.zeros((n, FR_N))
    truths = np.zeros((n, TR_N))
    states = np.zeros((n, st.size))
    for k in range(n):
        plant_advance(st, mp, rng, np.asarray(duty, float), True, *NO_LOAD, frame, truth)
        frames[k] = frame
        truths[k] = truth
        states[k] = st
    return frames, truths, states


def test_capture_delay_gives_the_predicted_duty_dependent_error():
    """Line a-b carries two pulses of width d Ts/2 per period (centre-aligned, legs a/b at
    0.5 +- d/2).  Each registered pulse is wider by (1 - 2 V_th/Vdc) t_edge + t_fall - t_rise
    (here 25 - 35 = -10 ns), so the captured voltage is off by 2 dw Vdc/Ts = -14.4 mV at any
    duty -- until a registered pulse is shorter than the 111 ns minimum, where the whole
    line voltage d Vdc vanishes."""
    card = dataclasses.replace(
        MachineCard(), inertia_kgm2=1e3, current_noise_a=0.0, deadtime_s=0.0, dc_bus_adc_bits=24
    )
    mp = machine_params(card, bench=BenchConfig(voltage_capture=CAPTURE))
    ts = card.ts_s
    dw = CAPTURE.width_error_s()
    assert dw == pytest.approx(-10e-9, abs=1e-15)
    for d in (0.001, 0.002, 0.0025, 0.004, 0.01, 0.1, 0.5):
        frames, _, _ = _run_fixed_duty(mp, [0.5 + d / 2, 0.5 - d / 2, 0.5], 3)
        vdc = frames[-1, FR_VDC]
        w = d * ts / 2  # each of the two a-b pulses
        expected = 0.0 if w + dw < CAPTURE.min_pulse_s else (d + 2 * dw / ts) * vdc
        assert frames[-1, FR_VAB] == pytest.approx(expected, abs=1e-4), d
        # line b-c: pulses of d Ts/4 of negative polarity, registered narrower as well
        w_bc = d * ts / 4
        exp_bc = 0.0 if w_bc + dw < CAPTURE.min_pulse_s else -(d / 2 + 2 * dw / ts) * vdc
        assert frames[-1, FR_VBC] == pytest.approx(exp_bc, abs=1e-4), d


def test_capture_threshold_on_slow_edges_and_jitter():
    """A pulse shorter than its edge ramp peaks at w/t_edge of the bus: below V_th/Vdc it is
    lost, above it registers 2 (w - (V_th/Vdc) t_edge) wide; with jitter sigma on each of
    the 4 edges of a period the captured line voltage scatters by 2 sigma Vdc/Ts around
    the mean error."""
    card = dataclasses.replace(
        MachineCard(), inertia_kgm2=1e3, current_noise_a=0.0, deadtime_s=0.0, dc_bus_adc_bits=24
    )
    slow = VoltageCapture(threshold_pu=0.5, edge_time_s=400e-9, resolution_bits=24)
    mp = machine_params(card, bench=BenchConfig(voltage_capture=slow))
    ts = card.ts_s
    for d, seen in ((0.0036, False), (0.0044, True)):  # pulses 180 ns / 220 ns vs 200 ns
        frames, _, _ = _run_fixed_duty(mp, [0.5 + d / 2, 0.5 - d / 2, 0.5], 2)
        vdc = frames[-1, FR_VDC]
        w = d * ts / 2
        registered = 2.0 * (w - 0.5 * slow.edge_time_s) if seen else 0.0
        assert frames[-1, FR_VAB] == pytest.approx(2 * registered / ts * vdc, abs=1e-4)
    sigma = 2e-9
    jit = dataclasses.replace(CAPTURE, jitter_s=sigma)
    mp = machine_params(card, bench=BenchConfig(voltage_capture=jit))
    frames, _, _ = _run_fixed_duty(mp, [0.55, 0.45, 0.5], 3000, seed=7)
    vdc = frames[-1, FR_VDC]
    err = frames[:, FR_VAB] - (0.1 + 2 * CAPTURE.width_error_s() / ts) * vdc
    assert abs(err.mean()) < 1e-4
    assert err.std() == pytest.approx(2 * sigma * vdc / ts, rel=0.08)


def test_thermal_model_rise_follows_i2r_over_its_time_constant():
    """Locked rotor, constant voltage, no tempco: P = 1.5 R |i|^2 is constant and the winding
    follows T_amb + P R_th (1 - exp(-t/tau)).  With the copper tempco the resistance is
    R_ref (1 + alpha (T - T_ref)) and the current falls as V/R(T)."""
    tau = 0.03
    card = ideal_machine(
        inertia_kgm2=1e3,
        deadtime_s=0.0,
        thermal_resistance_k_per_w=10.0,
        thermal_time_constant_s=tau,
        copper_tempco_per_k=0.0,
    )
    bench = BenchConfig(thermal=Thermal(ambient_c=25.0, initial_winding_c=25.0))
    mp = machine_params(card, bench=bench)
    duty = [0.53, 0.485, 0.485]  # v_alpha = 0.03 Vdc = 2.16 V -> i = 5.4 A
    n = 1000
    _, truths, states = _run_fixed_duty(mp, duty, n, i_alpha0=2.16 / 0.4)  # in steady state
    t = (np.arange(n) + 1) * card.ts_s
    i2 = truths[:, TR_IA] ** 2  # i_alpha = i_a
    p_cu = 1.5 * card.resistance_ohm * i2[-100:].mean()
    assert p_cu == pytest.approx(1.5 * card.resistance_ohm * (2.16 / 0.4) ** 2, rel=0.01)
    expected = 25.0 + p_cu * 10.0 * (1.0 - np.exp(-t / tau))
    assert np.abs(states[:, PS_TW] - expected).max() < 0.005 * p_cu * 10.0
    # with the tempco: R(T) and the current follow the winding temperature
    card = dataclasses.replace(card, copper_tempco_per_k=0.00393, thermal_time_constant_s=0.01)
    mp = machine_params(card, bench=bench)
    _, truths, states = _run_fixed_duty(mp, duty, 1000)
    st = states[-1]
    r_t = card.resistance_ohm * (1 + 0.00393 * (st[PS_TW] - 25.0))
    assert winding_resistance(st, mp) == pytest.approx(r_t, rel=1e-12)
    assert st[PS_TW] - 25.0 > 30.0
    assert truths[-1, TR_IA] == pytest.approx(2.16 / r_t, rel=0.01)
    # steady state: dT = 1.5 V^2/R(T) R_th
    assert st[PS_TW] - 25.0 == pytest.approx(1.5 * 2.16**2 / r_t * 10.0, rel=0.01)


def test_current_sampling_skew_samples_earlier():
    """Phase a sampled 20 us before the valley: in the zero vector of a locked rotor the
    current decays as exp(-R t/L), so the earlier sample is larger by exp(R s/L)."""
    card = ideal_machine(inertia_kgm2=1e3, deadtime_s=0.0)
    skew = 20e-6
    mp = machine_params(card, bench=BenchConfig(current_sample_skew_s=(skew, 0.0, 0.0)))
    frames, truths, _ = _run_fixed_duty(mp, [0.53, 0.485, 0.485], 40)
    gain = math.exp(card.resistance_ohm * skew / card.inductance_h)
    assert frames[-1, FR_IA] == pytest.approx(truths[-1, TR_IA] * gain, rel=1e-5)
    assert frames[-1, FR_IA] != pytest.approx(truths[-1, TR_IA], rel=1e-3)


def _locus_h6(tmp_path, load_pu: float, h6: float, h5: float = 0.0, h7: float = 0.0):
    """6th order of |lambda^| / mean |lambda^| and of theta~ [rad] (complex, against the rotor
    angle) of an encoder drive at 300 rpm under an active load (an LPF flux estimate at 2 Hz:
    unity gain for the 5th/7th, a constant lead on the fundamental)."""
    card = ideal_machine(deadtime_s=0.0)
    bench = {
        k: v
        for k, v in (
            ("spatial_saturation_h6_pu", h6),
            ("spatial_saturation_h5_pu", h5),
            ("spatial_saturation_h7_pu", h7),
        )
        if v
    }
    sc = make_scenario(
        tmp_path,
        card,
        name=f"sat_{load_pu}_{h6}_{h5}_{h7}",
        duration_s=0.9,
        speed_rpm=[[0.0, 0.0], [0.2, 300.0]],
        load_type="active",
        load_pu=[[0.0, 0.0], [0.3, 0.0], [0.4, load_pu]],
        steady_window_s=[0.6, 0.9],
        driving="encoder",
        bench=bench,
        observers={"flux": {"variant": "lpf", "cutoff_hz": 2.0, "voltage_source": "measured"}},
    )
    r = run_scenario(sc, progress=False)
    e = r.estimate("flux")[6000:9000]
    th = r.truth[6000:9000, TR_THETA_E]
    mag = np.hypot(e[:, ES_LA], e[:, ES_LB])
    err = np.angle(np.exp(1j * (np.arctan2(e[:, ES_LB], e[:, ES_LA]) - th)))
    return harmonic(mag, th, 6) / mag.mean(), harmonic(err - np.mean(err), th, 6)


def test_spatial_saturation_6th_order_of_flux_grows_with_load(tmp_path):
    """|lambda_pm| = lambda |1 + (h/2)(e^{-j6th} + e^{j6th})| has a 6th order of
    h = s6 (|i|/I_rated)^2: the flux estimate (an LPF at 2 Hz, 300 rpm: unity gain for the
    5th/7th) shows it growing with the load square.  The drive's own 6th order without the
    effect (linear in the load, 0.8 % at half load and 1.5 % at full load here, not from
    R: the same with R = 0) is taken out as a complex difference."""
    s6 = 0.03
    got = []
    for load in (0.5, 1.0, 1.25):
        sat = abs(_locus_h6(tmp_path, load, s6)[0] - _locus_h6(tmp_path, load, 0.0)[0])
        assert sat == pytest.approx(s6 * load**2, rel=0.15), load
        got.append(sat)
    assert got[0] < got[1] < got[2]
    assert abs(_locus_h6(tmp_path, 0.0, s6)[0]) < 0.002


def test_unequal_5th_and_7th_move_the_flux_angle_by_their_difference(tmp_path):
    """In the rotor frame lambda (h5 e^{-j6th} + h7 e^{j6th}) puts (h5 + h7) cos 6th on d and
    (h7 - h5) sin 6th on q: the flux angle ripples by (h7 - h5) rad, the radius by h5 + h7
    (h = s (|i|/I_rated)^2).  The plant, seen through a 2 Hz LPF at 300 rpm (unity gain at
    the 5th and 7th), against that formula at half load: the even split (the old
    spatial_saturation_h6_pu) moves no angle, a 5th or a 7th alone moves angle and radius by
    its size, a 5th and 7th of opposite sign move the angle and not the radius.  The drive's
    own 6th order (no saturation) is taken out as a complex difference.  (At half load the
    harmonics' own current dependence, which changes the incremental inductance seen by the
    5th and 7th in opposite senses, stays under 10 % of the ripple.)"""
    s, load = 0.03, 0.5
    base_mag, base_ang = _locus_h6(tmp_path, load, 0.0)
    for h6, h5, h7 in ((s, 0.0, 0.0), (0.0, 0.0, s), (0.0, s, 0.0), (0.0, -s / 2, s / 2)):
        mag, ang = _locus_h6(tmp_path, load, h6, h5, h7)
        p5, p7 = h6 / 2 + h5, h6 / 2 + h7
        x = load**2
        assert abs(ang - base_ang) / x == pytest.approx(abs(p7 - p5), abs=0.15 * s), (h5, h7)
        assert abs(mag - base_mag) / x == pytest.approx(abs(p5 + p7), abs=0.15 * s), (h5, h7)


def test_observer_model_errors_reach_the_observers(tmp_path):
    """bench.observer_model sets every observer's R^, L^, lambda^ from the card (one that
    sets its own keeps it); the kernel parameter rows carry them; a saved scenario reloads
    the same."""
    card = MachineCard()
    sc = make_scenario(
        tmp_path,
        None,
        name="om",
        duration_s=0.1,
        bench={"observer_model": {"r_pu": 0.97, "l_pu": 1.05, "lambda_pu": 1.02}},
        observers={"a": {"variant": "paper"}, "b": {"variant": "emf", "r_hat_ohm": 0.5}},
    )
    ds = DriveSetup(sc)
    a, b = ds.obs_params
    assert a[OP_R] == pytest.approx(0.97 * card.resistance_ohm)
    assert a[OP_L] == pytest.approx(1.05 * card.inductance_h)
    assert a[OP_LAM] == pytest.approx(1.02 * card.flux_linkage_vs)
    assert b[OP_R] == 0.5 and b[OP_L] == pytest.approx(1.05 * card.inductance_h)
    back = load_scenario(save_scenario(sc, tmp_path / "saved.yaml"))
    assert back.bench == sc.bench
    assert np.array_equal(DriveSetup(back).obs_params, ds.obs_params)


def test_paper_scenarios_run_on_the_paper_bench_and_bad_entries_are_refused(tmp_path):
    for name in ("paper_2pct_150load", "paper_4pct_fullload", "paper_6pct_stepload"):
        sc = load_scenario(CONFIG_DIR / "scenarios" / f"{name}.yaml")
        b = sc.bench
        assert b.voltage_capture is not None and b.thermal is not None
        assert b.observer_model is not None and b.observer_model.r_pu != 1.0
        assert b.spatial_saturation_h6_pu > 0 and b.current_sample_skew_s is not None
        assert all(o.r_hat_ohm is not None for o in sc.observers.values())
    card = MachineCard()
    with pytest.raises(ConfigError, match="bench.voltage_capture"):
        parse_bench("x.yaml", {"voltage_capture": {"threshold_pu": "high"}}, card)
    with pytest.raises(ConfigError, match="unknown key"):
        parse_bench("x.yaml", {"capture": {}}, card)
    # a card without a thermal model keeps its resistance
    cold = dataclasses.replace(card, thermal_resistance_k_per_w=0.0)
    assert machine_params(cold, bench=parse_bench("x.yaml", {"thermal": {}}, cold))[MP_TH_ON] == 0.0
    with pytest.raises(ConfigError, match="current_sample_skew_s"):
        parse_bench("x.yaml", {"current_sample_skew_s": [0.0, 1.0]}, card)
    # the ideal bench leaves the plant's parameter vector as it was
    assert np.array_equal(machine_params(card, bench=BenchConfig()), machine_params(card))


def test_rig_card_for_the_step_load_differs_from_the_default_only_in_inertia():
    """paper_rig = default_spm + the dyno's inertia, J = T_L/(e w_n dip) for a zeta = 1 PI
    speed loop of 10 Hz bandwidth (w_n = 2 pi 10/2.48) and the paper's 90 rpm dip; the step
    scenario runs on it, the default card keeps the motor-only 1.5e-4."""
    from fluxdrive.core.machine import load_machine

    default = load_machine(CONFIG_DIR / "machines" / "default_spm.yaml")
    rig = load_machine(CONFIG_DIR / "machines" / "paper_rig.yaml")
    assert default.inertia_kgm2 == 1.5e-4
    assert dataclasses.replace(rig, name=default.name, inertia_kgm2=default.inertia_kgm2) == default
    w_n = 2 * math.pi * 10.0 / 2.4826
    dip = 90.0 * 2 * math.pi / 60
    assert rig.inertia_kgm2 == pytest.approx(
        default.rated_torque_nm / (math.e * w_n * dip), rel=0.01
    )
    # the well-damped loop is back within 10 % of 180 rpm (1/5 of the dip) inside 0.2 s
    x = np.linspace(1.0, 10.0, 90001)
    x_back = x[np.argmin(np.abs(x * np.exp(1.0 - x) - 0.2))]
    assert x_back / w_n < 0.2
    sc = load_scenario(CONFIG_DIR / "scenarios" / "paper_6pct_stepload.yaml")
    assert sc.machine == dataclasses.replace(rig, name="default_spm+paper_rig")
