"""The bench's machine and inverter effects (docs/engine.md, "Non-ideal bench"): inductance
saturation, phase asymmetry, sensor gains, output capacitance, switching noise -- each
against the circuit equation it follows from, on a locked rotor driven at fixed duties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.core.bench import (
    BenchConfig,
    InductanceSaturation,
    PhaseAsymmetry,
    SwitchingNoise,
    parse_bench,
)
from fluxdrive.core.blocks import rng_new
from fluxdrive.core.machine import ConfigError, MachineCard
from fluxdrive.drive.plant import (
    FR_IA,
    FR_IC,
    FR_N,
    MP_CIRC_ON,
    MP_LI_AA,
    MP_LI_BB,
    MP_LM_AA,
    MP_LM_BB,
    MP_RM_AA,
    MP_RM_BB,
    PS_IA,
    PS_IB,
    TR_IA,
    TR_IC,
    TR_N,
    _simulate_period,
    load_config,
    machine_params,
    plant_advance,
    plant_state,
)
from helpers_engine import ideal_machine

NO_LOAD = (np.array([0.0]), np.array([0.0]), load_config(0.0, 0.0))
# amplitude-invariant Clarke (2 x 3) and its inverse for zero-sequence-free vectors (3 x 2)
CLARKE = np.array([[2.0, -1.0, -1.0], [0.0, math.sqrt(3.0), -math.sqrt(3.0)]]) / 3.0
INV_CLARKE = np.array([[1.0, 0.0], [-0.5, math.sqrt(3.0) / 2], [-0.5, -math.sqrt(3.0) / 2]])


def _run(mp, duties, i_ab0=(0.0, 0.0), seed=1):
    """Locked rotor at theta_e = 0 (alpha = d axis): frames and truths for a duty sequence."""
    st = plant_state()
    st[PS_IA], st[PS_IB] = i_ab0
    rng = rng_new(seed)
    frame = np.zeros(FR_N)
    truth = np.zeros(TR_N)
    frames = np.zeros((len(duties), FR_N))
    truths = np.zeros((len(duties), TR_N))
    for k, duty in enumerate(duties):
        plant_advance(st, mp, rng, np.asarray(duty, float), True, *NO_LOAD, frame, truth)
        frames[k] = frame
        truths[k] = truth
    return frames, truths


def _alpha_beta(phases: np.ndarray) -> np.ndarray:
    ab = phases @ CLARKE.T
    return ab[:, 0] + 1j * ab[:, 1]


def _duty_for(v_ab: complex, vdc: float) -> list[float]:
    """Duties whose leg voltages (minus their mean) have the alpha/beta vector v_ab."""
    legs = INV_CLARKE @ np.array([v_ab.real, v_ab.imag])
    return list(0.5 + legs / vdc)


def _bisect(f, lo: float, hi: float) -> float:
    for _ in range(64):  # below one ulp of [-10, 10]
        mid = 0.5 * (lo + hi)
        if (f(mid) > 0.0) == (f(hi) > 0.0):
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def _newton_fd(f, x0: np.ndarray) -> np.ndarray:
    """Root of a vector function by Newton with a finite-difference Jacobian."""
    x = x0.astype(float)
    for _ in range(100):
        fx = f(x)
        h = 1e-7 * max(1e-3, float(np.abs(x).max()))
        jac = np.column_stack([(f(x + h * e) - fx) / h for e in np.eye(x.size)])
        x = x - np.linalg.solve(jac, fx)
    return x


def _rk4(f, y0: np.ndarray, t_end: float, steps: int) -> np.ndarray:
    y = y0.astype(float)
    h = t_end / steps
    for _ in range(steps):
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y


def _complex_parts(m: np.ndarray) -> tuple[float, complex]:
    """A real symmetric 2x2 map of x = x_a + j x_b as m0 x + m2 conj(x)."""
    return 0.5 * (m[0, 0] + m[1, 1]), 0.5 * (m[0, 0] - m[1, 1]) + 1j * m[0, 1]


# ------------------------------------------------------------------ inductance saturation
SAT = InductanceSaturation(q_pu=0.3, q_exponent=2.0, d_pu=0.2, d_exponent=2.0, cross_pu=0.4)


def _q_flux_of_current(i_q: float, card: MachineCard) -> float:
    """psi_q for i_q on the q axis (no d current): invert i_q = y (1 + k_q |y|^T) psi_b/L."""
    psi_b = card.inductance_h * card.rated_current_a

    def g(y):
        return y * (1.0 + SAT.q_pu * abs(y) ** SAT.q_exponent) * card.rated_current_a - i_q

    return _bisect(g, -10.0, 10.0) * psi_b


def _q_incremental_inductance(i_q: float, card: MachineCard) -> float:
    """d(psi_q)/d(i_q) = L / (1 + (T + 1) k_q |y|^T) on the q axis."""
    y = _q_flux_of_current(i_q, card) / (card.inductance_h * card.rated_current_a)
    return card.inductance_h / (1.0 + (SAT.q_exponent + 1.0) * SAT.q_pu * abs(y) ** SAT.q_exponent)


@pytest.mark.parametrize("level_pu", [0.5, 1.5])
def test_saturated_q_axis_step_takes_the_time_the_flux_map_predicts(level_pu):
    """Locked rotor, q-axis current at I0, a voltage step to R I1: L_q(i) di/dt = V - R i, so
    the current reaches I0 + 0.632 (I1 - I0) after int L_inc(i)/(V - R i) di.  The unsaturated
    machine takes L/R ln(1/0.368) = 2.0 ms; the saturated one less, more so at 1.5 pu."""
    card = ideal_machine(inertia_kgm2=1e3, deadtime_s=0.0)
    mp = machine_params(card, bench=BenchConfig(inductance_saturation=SAT))
    r = card.resistance_ohm
    i0 = level_pu * card.rated_current_a
    i1 = i0 + 0.5
    duty = _duty_for(1j * r * i1, card.dc_bus_v)
    _, truths = _run(mp, [duty] * 150, i_ab0=(0.0, i0))
    i_q = _alpha_beta(truths[:, TR_IA : TR_IC + 1]).imag
    t = (np.arange(len(i_q)) + 1) * card.ts_s
    target = i0 + (1.0 - math.exp(-1.0)) * (i1 - i0)
    t_meas = float(np.interp(target, i_q, t))

    def integrand(i):
        return _q_incremental_inductance(i, card) / (r * (i1 - i))

    grid = np.linspace(i0, target, 201)  # Simpson's rule (a smooth integrand)
    vals = np.array([integrand(i) for i in grid])
    t_pred = float(
        (grid[1] - grid[0])
        / 3
        * (vals[0] + vals[-1] + 4 * vals[1:-1:2].sum() + 2 * vals[2:-1:2].sum())
    )
    assert t_meas == pytest.approx(t_pred, rel=0.01)
    tau_linear = card.inductance_h / r
    assert t_pred < 0.95 * tau_linear  # the effect is there (L_inc below L)
    assert t_pred / tau_linear == pytest.approx(
        _q_incremental_inductance(i0 + 0.3, card) / card.inductance_h, rel=0.02
    )


def test_cross_saturation_follows_the_flux_map_in_both_axes():
    """With d and q current the flux map couples the axes: the step response of both
    currents follows d(psi)/dt = v - R i(psi), integrated here from the map's equations
    by a fine RK4 (an independent integrator of the map's equations) -- to 1 % of the step."""

    card = ideal_machine(inertia_kgm2=1e3, deadtime_s=0.0)
    mp = machine_params(card, bench=BenchConfig(inductance_saturation=SAT))
    r, l_h, i_r = card.resistance_ohm, card.inductance_h, card.rated_current_a
    psi_b = l_h * i_r
    s, u, v = SAT, SAT.cross_exponent_d, SAT.cross_exponent_q

    def current(psi):
        x, y = psi / psi_b
        i_d = x * (
            1
            + s.d_pu * abs(x) ** s.d_exponent
            + s.cross_pu / (v + 2) * abs(x) ** u * abs(y) ** (v + 2)
        )
        i_q = y * (
            1
            + s.q_pu * abs(y) ** s.q_exponent
            + s.cross_pu / (u + 2) * abs(x) ** (u + 2) * abs(y) ** v
        )
        return np.array([i_d, i_q]) * i_r

    i_start = np.array([-0.8 * i_r, 0.8 * i_r])
    v_step = r * np.array([-0.6 * i_r, 1.3 * i_r])
    psi = _newton_fd(lambda p: current(p) - i_start, i_start * l_h)
    n = 60
    expected = np.zeros((n, 2))
    for k in range(n):
        psi = _rk4(lambda p: v_step - r * current(p), psi, card.ts_s, 50)
        expected[k] = current(psi)
    t = (np.arange(n) + 1) * card.ts_s
    duty = _duty_for(complex(*v_step), card.dc_bus_v)
    _, truths = _run(mp, [duty] * n, i_ab0=tuple(i_start))
    got = _alpha_beta(truths[:, TR_IA : TR_IC + 1])
    step = np.abs(v_step / r - i_start)
    assert np.abs(got.real - expected[:, 0]).max() < 0.01 * step[0]
    assert np.abs(got.imag - expected[:, 1]).max() < 0.01 * step[1]
    # the coupling is visible: a linear machine's d current would not move the same way
    linear = i_start[0] + (v_step[0] / r - i_start[0]) * (1 - np.exp(-r * t / l_h))
    assert np.abs(got.real - linear).max() > 0.05 * step[0]


def test_effects_off_change_nothing_and_the_flux_branch_matches_the_exact_rl_step():
    """Absent or neutral entries keep the ideal plant bit for bit; the flux-integrating
    branch of a linear machine agrees with the exact RL step response."""
    card = ideal_machine(inertia_kgm2=1e3)
    duties = [_duty_for(3.0 * np.exp(1j * 0.003 * k), card.dc_bus_v) for k in range(200)]
    ref, _ = _run(machine_params(card), duties)
    neutral = BenchConfig(
        inductance_saturation=InductanceSaturation(),
        phase_asymmetry=PhaseAsymmetry(),
        current_sensor_gain=(1.0, 1.0, 1.0),
        switching_noise=SwitchingNoise(ringing_a=0.0, window_s=1e-6),
    )
    mp = machine_params(card, bench=neutral)
    assert mp[MP_CIRC_ON] == 0.0
    same, _ = _run(mp, duties)
    assert np.array_equal(ref, same)
    # force the flux-state integration of the same linear, balanced machine
    for k in (MP_CIRC_ON, MP_LM_AA, MP_LM_BB, MP_LI_AA, MP_LI_BB, MP_RM_AA, MP_RM_BB):
        mp[k] = 1.0
    flux, _ = _run(mp, duties)
    i_ref = ref[:, FR_IA : FR_IC + 1]
    assert np.abs(flux[:, FR_IA : FR_IC + 1] - i_ref).max() < 1e-4 * np.abs(i_ref).max()


# ------------------------------------------------------------------ phase asymmetry, sensor gain
def _fit_sequences(i_ab: np.ndarray, t: np.ndarray, w: float) -> tuple[complex, complex]:
    """Least-squares P, N of i = P e^{jwt} + N e^{-jwt}."""
    a = np.column_stack([np.exp(1j * w * t), np.exp(-1j * w * t)])
    (p, n), *_ = np.linalg.lstsq(a, i_ab, rcond=None)
    return p, n


def _rotating_voltage_run(mp, card, v_amp, f_hz, n):
    w = 2 * math.pi * f_hz
    ts = card.ts_s
    # the duty of period k acts over [k Ts, (k+1) Ts]: its mean is the voltage at mid-period
    duties = [_duty_for(v_amp * np.exp(1j * w * (k + 0.5) * ts), card.dc_bus_v) for k in range(n)]
    frames, truths = _run(mp, duties)
    t = (np.arange(n) + 1) * ts
    keep = t > 0.04  # after the transient (L/R = 2 ms)
    return frames[keep], truths[keep], t[keep], w


def test_unbalanced_resistance_and_inductance_give_the_predicted_negative_sequence():
    """v = R_M i + L_M di/dt with per-phase R, L: R_M = r0 + r2 conj(), L_M likewise, and a
    positive-sequence voltage V e^{jwt} drives P e^{jwt} + N e^{-jwt} with
    N* = -(r2* + jw l2*) P/(r0 + jw l0),  V = P [(r0 + jw l0) - |r2 + jw l2|^2/(r0 + jw l0)]
    (|r2 + jw l2|^2 meaning (r2 + jw l2)(r2* + jw l2*)).  In dq: a 2nd order of |N|."""
    card = ideal_machine(inertia_kgm2=1e3, deadtime_s=0.0)
    asym = PhaseAsymmetry(resistance_pu=(1.5, 1.0, 0.9), inductance_pu=(1.0, 1.2, 1.0))
    mp = machine_params(card, bench=BenchConfig(phase_asymmetry=asym))
    v_amp, f_hz = 3.0, 50.0
    _, truths, t, w = _rotating_voltage_run(mp, card, v_amp, f_hz, 800)
    p, n = _fit_sequences(_alpha_beta(truths[:, TR_IA : TR_IC + 1]), t, w)
    rm = card.resistance_ohm * CLARKE @ np.diag(asym.resistance_pu) @ INV_CLARKE
    lm = card.inductance_h * CLARKE @ np.diag(asym.inductance_pu) @ INV_CLARKE
    r0, r2 = _complex_parts(rm)
    l0, l2 = _complex_parts(lm)
    a = r0 + 1j * w * l0
    b = r2 + 1j * w * l2
    b_conj = np.conj(r2) + 1j * w * np.conj(l2)
    p_pred = v_amp / (a - b * b_conj / a)
    n_pred = np.conj(-b_conj * p_pred / a)
    assert abs(p) == pytest.approx(abs(p_pred), rel=0.01)
    assert abs(n) == pytest.approx(abs(n_pred), rel=0.01)
    assert abs(n) > 0.05 * abs(p)
    assert np.angle(n / n_pred) == pytest.approx(0.0, abs=0.02)


def test_sensor_gain_mismatch_gives_the_predicted_second_order_in_dq():
    """Measured phases g_j i_j: alpha/beta M_g i = g0 i + g2 conj(i), so a balanced current
    P e^{jwt} reads g0 P e^{jwt} + g2 P* e^{-jwt}: in dq a 2nd order of |g2| |P|."""
    card = ideal_machine(inertia_kgm2=1e3, deadtime_s=0.0)
    gains = (1.03, 0.98, 1.0)
    mp = machine_params(card, bench=BenchConfig(current_sensor_gain=gains))
    frames, truths, t, w = _rotating_voltage_run(mp, card, 3.0, 50.0, 700)
    p_true, n_true = _fit_sequences(_alpha_beta(truths[:, TR_IA : TR_IC + 1]), t, w)
    assert abs(n_true) < 1e-3 * abs(p_true)  # the machine is balanced
    i_meas = _alpha_beta(frames[:, FR_IA : FR_IC + 1])
    p_meas, n_meas = _fit_sequences(i_meas, t, w)
    g0, g2 = _complex_parts(CLARKE @ np.diag(gains) @ INV_CLARKE)
    assert abs(p_meas) == pytest.approx(g0 * abs(p_true), rel=1e-3)
    assert abs(n_meas) == pytest.approx(abs(g2) * abs(p_true), rel=0.01)
    # the dq view: i_dq = i e^{-jwt} oscillates at 2w with amplitude |N|
    i_dq = i_meas * np.exp(-1j * w * t)
    assert (np.abs(i_dq - i_dq.mean()).max()) == pytest.approx(abs(n_meas), rel=0.02)


# ------------------------------------------------------------------ output capacitance
def test_output_capacitance_makes_the_deadtime_error_current_dependent():
    """In the deadtime window the current swings the leg through 2 C_oss over V_dc in
    t_c = 2 C_oss V_dc/|i|: the volt-second loss per period is V_dc (t_d - t_c/2) for
    t_c <= t_d and V_dc t_d^2/(2 t_c) above (the turn-on ends the window), instead of
    V_dc t_d at any current."""
    coss = 1.2e-9
    card = ideal_machine(inertia_kgm2=1e3, inductance_h=10.0)  # the current holds over a period
    mp = machine_params(card, bench=BenchConfig(output_capacitance_f=coss))
    vdc, td, ts = card.dc_bus_v, card.deadtime_s, card.ts_s

    def loss_s(i):
        tc = 2 * coss * vdc / abs(i)
        return td - tc / 2 if tc <= td else td * td / (2 * tc)

    for i_a in (8.0, 1.0, 0.2, 0.05, 0.02, -0.3):
        st = plant_state()
        st[PS_IA] = i_a  # i_a, i_b = i_c = -i_a/2
        vs = np.zeros(12)
        _simulate_period(
            st,
            mp,
            0.5,
            0.5,
            0.5,
            True,
            0.0,
            np.zeros(20),
            vs,
            np.zeros((1, 1)),
            np.zeros((1, 1)),
            np.zeros(3),
        )
        expected = -math.copysign(1.0, i_a) * vdc * (loss_s(i_a) + loss_s(i_a / 2))
        assert vs[0] == pytest.approx(expected, rel=1e-4), i_a
    # the ideal commutation loses V_dc t_d per leg at any current
    assert loss_s(1e6) == pytest.approx(td)
    assert vdc * (loss_s(0.05) + loss_s(0.025)) / ts < 0.25 * 2 * vdc * td / ts


# ------------------------------------------------------------------ switching noise
def test_switching_noise_follows_the_edges_before_the_sample():
    """Leg a at 98 % duty with i_a > 0 turns its top switch off dt = 1 us before the valley
    sample: every phase's sample gets sqrt(s_w^2 + A^2 exp(-2 dt/tau)) of noise; at 50 % no
    edge is within the window and the white noise s_w is all."""
    ring = SwitchingNoise(ringing_a=0.2, window_s=2e-6, decay_s=0.5e-6)
    card = ideal_machine(inertia_kgm2=1e3, resistance_ohm=10.0, current_noise_a=0.02)
    mp = machine_params(card, bench=BenchConfig(switching_noise=ring))
    n = 3000
    for d_a, dt in ((0.98, 0.01 * card.ts_s), (0.5, None)):  # top off at (1 + d) Ts/2
        duty = [d_a, 0.5, 0.5]
        v_alpha = card.dc_bus_v * (2 * d_a - 1.0) / 3
        frames, truths = _run(mp, [duty] * n, i_ab0=(v_alpha / card.resistance_ohm, 0.0), seed=5)
        err = frames[:, FR_IA : FR_IC + 1] - truths[:, TR_IA : TR_IC + 1]
        sigma = 0.02 if dt is None else math.hypot(0.02, 0.2 * math.exp(-dt / 0.5e-6))
        assert np.abs(err.mean(axis=0)).max() < 4 * sigma / math.sqrt(n)
        assert err.std(axis=0) == pytest.approx([sigma] * 3, rel=0.05)
    again, _ = _run(mp, [[0.98, 0.5, 0.5]] * 50, i_ab0=(v_alpha / 10.0, 0.0), seed=5)
    assert np.array_equal(
        again, _run(mp, [[0.98, 0.5, 0.5]] * 50, i_ab0=(v_alpha / 10.0, 0.0), seed=5)[0]
    )


def test_bad_effect_entries_are_refused_with_the_key():
    card = MachineCard()
    with pytest.raises(ConfigError, match="bench.phase_asymmetry.resistance_pu"):
        parse_bench("x.yaml", {"phase_asymmetry": {"resistance_pu": [1.0, 0.0, 1.0]}}, card)
    with pytest.raises(ConfigError, match="bench.current_sensor_gain"):
        parse_bench("x.yaml", {"current_sensor_gain": [1.0, 1.0]}, card)
    with pytest.raises(ConfigError, match="bench.inductance_saturation"):
        parse_bench("x.yaml", {"inductance_saturation": {"q_gain": 0.1}}, card)
    raw = {
        "inductance_saturation": {"q_pu": 0.1},
        "phase_asymmetry": {"resistance_pu": [1.1, 1.0, 1.0]},
        "current_sensor_gain": [1.01, 1.0, 0.99],
        "output_capacitance_f": 1e-9,
        "switching_noise": {"ringing_a": 0.1, "window_s": 1e-6},
    }
    bench = parse_bench("x.yaml", raw, card)
    assert parse_bench("x.yaml", bench.to_raw(), card) == bench


def test_experiment_bench_option_swaps_only_the_paper_bench(tmp_path):
    """`experiment --bench FILE`: a scenario on the paper bench runs on FILE, an ideal one
    stays ideal; a file that changes the observers' model is refused (they took theirs from
    the paper bench when the scenario was loaded)."""
    from fluxdrive.drive.scenario import CONFIG_DIR, load_bench_file
    from fluxdrive.experiments.common import PAPER_BENCH, Ctx

    effects = CONFIG_DIR / "benches" / "paper_lab_effects.yaml"
    ctx = Ctx(bench=effects, echo=False)
    on_paper = ctx.build(base="paper_2pct_150load")
    ideal = ctx.build(base="paper_2pct_150load", bench={})
    swapped, kept = ctx._on_bench((on_paper, ideal))
    assert swapped.bench == load_bench_file(effects, on_paper.machine)
    assert swapped.bench.inductance_saturation is not None
    assert (
        swapped.bench.voltage_capture
        == load_bench_file(PAPER_BENCH, on_paper.machine).voltage_capture
    )
    assert kept.bench == BenchConfig()
    other_model = tmp_path / "other_model.yaml"
    other_model.write_text(f"base: {PAPER_BENCH}\nobserver_model: {{r_pu: 1.0}}\n")
    with pytest.raises(ConfigError, match="observer_model"):
        Ctx(bench=other_model, echo=False)._on_bench(on_paper)
