"""The literal `paper` observer against eqs. (5)-(8) on synthetic frames, the EMF baseline's
PLL/LPF against their stated design, and `paper_robust`'s documented departures."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.core.machine import MachineCard
from fluxdrive.core.transforms import inv_clarke
from fluxdrive.drive.observers import (
    ES_LA,
    ES_LB,
    ES_TH,
    ES_W,
    OS_INIT,
    OS_IPA,
    OS_IPB,
    OS_PLL_I,
    OS_TH,
    OS_WF,
    KernelObserver,
    observer_config,
)
from fluxdrive.drive.plant import FR_IA, FR_IB, FR_IC, FR_N, FR_SEQ, FR_VAB, FR_VBC, FR_VCA

CARD = MachineCard()
TS = CARD.ts_s


def synthetic_frames(
    n: int,
    w_e: float,
    lam: float,
    i_amp: float = 0.0,
    i_phase: float = 0.0,
    v_off=(0.0, 0.0),
    inj_amp: float = 0.0,
    inj_hz: float = 0.0,
    theta0: float = 0.3,
):
    """Frames of a rotating magnet flux lam e^{j theta}, theta = theta0 + w_e t, with a
    current i_amp e^{j(theta + i_phase)} (plus an optional stationary-frame alpha current
    at inj_hz), measured voltages v = R i + d(lam_pm + L i)/dt + v_off as step averages
    (the plant's convention: frame k holds the average voltage over [t_{k-1}, t_k])."""
    r, lind = CARD.resistance_ohm, CARD.inductance_h
    k = np.arange(n + 1)
    th = theta0 + w_e * k * TS
    i = i_amp * np.exp(1j * (th + i_phase)) + inj_amp * np.sin(2 * math.pi * inj_hz * k * TS)
    lam_s = lam * np.exp(1j * th) + lind * i
    v = r * 0.5 * (i[1:] + i[:-1]) + np.diff(lam_s) / TS + complex(*v_off)
    fr = np.zeros((n + 1, FR_N))
    for kk in range(n + 1):
        a, b, c = inv_clarke(i[kk].real, i[kk].imag)
        fr[kk, FR_IA], fr[kk, FR_IB], fr[kk, FR_IC] = a, b, c
        if kk > 0:
            pa, pb, pc = inv_clarke(v[kk - 1].real, v[kk - 1].imag)
            fr[kk, FR_VAB], fr[kk, FR_VBC], fr[kk, FR_VCA] = pa - pb, pb - pc, pc - pa
        fr[kk, FR_SEQ] = kk
    return fr, th, i


def locked(obs: KernelObserver, th0: float, w_e: float, i0: complex) -> None:
    """Start the observer locked (PLL at the true angle and frequency) at frame 0."""
    obs.reset()
    st = obs.state
    st[OS_INIT] = 1.0
    st[OS_TH] = th0
    st[OS_PLL_I] = w_e
    st[OS_WF] = w_e
    st[OS_IPA], st[OS_IPB] = i0.real, i0.imag


@pytest.mark.parametrize(
    "f_e_hz,cutoff_hz,v_off",
    [
        (4.0, 100.0, (0.0, 0.0)),  # 2 % speed, the paper's w_c
        (4.0, 100.0, (0.05, -0.03)),  # with a voltage offset (what the HPF is for)
        (20.0, 50.0, (0.02, 0.04)),  # 10 % speed, another cut-off
    ],
)
def test_paper_literal_returns_eq8_magnitude_and_phase(f_e_hz, cutoff_hz, v_off):
    """LPF 1/(s+w_c) x (1 - j w_c/w^e) = 1/s at w^e (eq. 8), then - L^ i (eq. 5): the rotating
    magnet flux comes back with its exact magnitude and phase; a DC offset V0 comes out as
    V0/w_c (1 - j w_c/w^e) (the HPF's residue, re-amplified by the inverse HPF)."""
    w_e = 2 * math.pi * f_e_hz
    lam = CARD.flux_linkage_vs
    n = int(0.6 / TS)
    fr, th, i = synthetic_frames(n, w_e, lam, i_amp=9.0, i_phase=math.pi / 2, v_off=v_off)
    # a slow PLL: its frequency stays at w_e although the offset ripples theta^
    obs = KernelObserver(observer_config("paper", cutoff_hz=cutoff_hz, pll_bandwidth_hz=0.2), CARD)
    locked(obs, th[1], w_e, i[0])
    est = obs.run(fr[1:])
    assert obs.config.inductance_term == "after_integration"
    assert obs.config.comp_freq_lpf_hz == 0.0 and obs.config.phase_detector == "atan"
    k0 = int(0.3 / TS)  # the LPF's start transient (tau = 1/w_c) has long decayed
    n_per = int(round(1.0 / f_e_hz / TS))
    sl = slice(k0, k0 + n_per * int((n - k0) // n_per))
    lam_hat = est[sl, ES_LA] + 1j * est[sl, ES_LB]
    w_c = 2 * math.pi * cutoff_hz
    # eq. (8) at the PLL's frequency estimate w^e used for sample k (its integrator after
    # sample k-1, reported as ES_W): [lam_s jw/(jw + w_c) + V0/w_c] (1 - j w_c/w^e) - L i
    w_hat = np.concatenate([[w_e], est[:-1, ES_W]])[sl]
    comp = 1 - 1j * w_c / w_hat
    lam_s = lam * np.exp(1j * th[1:][sl]) + CARD.inductance_h * i[1:][sl]
    pred = (
        lam_s * 1j * w_e / (1j * w_e + w_c) + complex(*v_off) / w_c
    ) * comp - CARD.inductance_h * i[1:][sl]
    ratio = lam_hat / pred
    # the implemented LPF (exact ZOH pole) is the continuous one delayed by Ts/2:
    # |error| <= w_e Ts/2 * w_e/w_c  (5e-5 at 2 % speed)
    tol = max(1e-4, 2 * w_e * TS / 2 * w_e / w_c)
    assert np.max(np.abs(np.abs(ratio) - 1.0)) < tol
    assert np.max(np.abs(np.angle(ratio))) < tol
    # and with w^e = w_e the magnet flux itself: |lambda| and theta exactly, plus the
    # offset's residue V0/w_c (1 - j w_c/w_e)
    resid = lam_hat - complex(*v_off) / w_c * (1 - 1j * w_c / w_e)
    ratio = resid / (lam * np.exp(1j * th[1:][sl]))
    # (w^e ripples by the offset's 1st-order theta~: a slow PLL keeps that below 1e-3)
    tol = 1e-3 if any(v_off) else 1e-4
    assert np.max(np.abs(np.abs(ratio) - 1.0)) < tol
    assert np.max(np.abs(np.angle(ratio))) < tol
    assert np.mean(est[sl, ES_W]) == pytest.approx(w_e, rel=1e-3)


def test_paper_literal_vs_robust_under_current_at_another_frequency():
    """eq. (5)'s order: v - R^ i is filtered and compensated at w^e, L^ i subtracted exactly.
    A current at another frequency (a 50 Hz d-axis sweep) is compensated at the wrong
    frequency and leaks into lambda_pm; paper_robust removes L^ di/dt before the filter and
    is exact for it."""
    w_e = 2 * math.pi * 4.0
    lam = CARD.flux_linkage_vs
    n = int(0.8 / TS)
    fr, th, i = synthetic_frames(n, w_e, lam, inj_amp=1.8, inj_hz=50.0)
    errs = {}
    for variant in ("paper", "paper_robust"):
        obs = KernelObserver(observer_config(variant), CARD)
        locked(obs, th[1], w_e, i[0])
        if variant == "paper_robust":
            from fluxdrive.drive.observers import OS_WCOMP

            obs.state[OS_WCOMP] = w_e
        est = obs.run(fr[1:])
        sl = slice(int(0.4 / TS), None)
        lam_hat = est[sl, ES_LA] + 1j * est[sl, ES_LB]
        errs[variant] = float(np.max(np.abs(lam_hat / (lam * np.exp(1j * th[1:][sl])) - 1)))
        errs[variant + "_theta"] = float(
            np.degrees(np.max(np.abs(np.angle(np.exp(1j * (est[sl, ES_TH] - th[1:][sl]))))))
        )
    # the leak: L I_inj (1/(j w_inj + w_c)) ((j w_inj + w_c)... ) -- order L I / lam = 6 %
    assert errs["paper"] > 0.02
    assert errs["paper_robust"] < 2e-3
    assert errs["paper_theta"] > 5 * errs["paper_robust_theta"]


def test_emf_baseline_pll_and_speed_lpf_match_the_stated_design():
    """Fig. 5: the EMF path's PLL is the stated 15 Hz type-2 loop (zeta 1) and its speed
    output passes the stated 20 Hz first-order LPF.  Measured on a synthetic EMF whose
    frequency is modulated: the response of w^ to w at f is
    w_n^2/(s^2 + 2 zeta w_n s + w_n^2) x w_l/(s + w_l)."""
    cfg = observer_config("emf", card=CARD)  # the default card: 1 kHz current loop
    assert (cfg.pll_bandwidth_hz, cfg.pll_damping, cfg.speed_lpf_hz) == (15.0, 1.0, 20.0)
    assert cfg.phase_detector == "atan"
    lam = CARD.flux_linkage_vs
    w0 = 2 * math.pi * 20.0  # 10 % speed: plenty of EMF
    for f_mod in (2.0, 15.0, 30.0):
        dw = 0.05 * w0
        n = int((1.0 + 6.0 / f_mod) / TS)
        t = np.arange(n + 1) * TS
        th = 0.2 + w0 * t - dw / (2 * math.pi * f_mod) * np.cos(2 * math.pi * f_mod * t)
        w = w0 + dw * np.sin(2 * math.pi * f_mod * t)
        lam_s = lam * np.exp(1j * th)
        v = np.diff(lam_s) / TS
        fr = np.zeros((n + 1, FR_N))
        for kk in range(1, n + 1):
            pa, pb, pc = inv_clarke(v[kk - 1].real, v[kk - 1].imag)
            fr[kk, FR_VAB], fr[kk, FR_VBC], fr[kk, FR_VCA] = pa - pb, pb - pc, pc - pa
            fr[kk, FR_SEQ] = kk
        obs = KernelObserver(cfg, CARD)
        locked(obs, th[1], w0, 0j)
        est = obs.run(fr[1:])
        k0 = int(1.0 / TS)
        tt = t[1:][k0:]
        ph = np.exp(-2j * math.pi * f_mod * tt)
        g = np.mean((est[k0:, ES_W] - w0) * ph) / np.mean((w[1:][k0:] - w0) * ph)
        s = 2j * math.pi * f_mod
        wn, wl = 2 * math.pi * 15.0, 2 * math.pi * 20.0
        g_design = wn * wn / (s * s + 2 * wn * s + wn * wn) * wl / (s + wl)
        assert abs(g) == pytest.approx(abs(g_design), rel=0.03), f_mod
        assert np.angle(g / g_design) == pytest.approx(0.0, abs=math.radians(3)), f_mod


def test_every_designed_loop_is_within_the_peaking_limit():
    """design_loops: the model of every drive's current and speed loop peaks by at most the
    stated 3 dB; the flux drive (25 Hz PLL) gets the full 10 Hz target, the EMF drive
    (15 Hz PLL + 20 Hz LPF) is held to what the limit allows (about 7 Hz)."""
    from fluxdrive.drive.control import design_loops

    paths = {"encoder": (150.0, 1.0, 0.0), "flux": (25.0, 1.0, 0.0), "emf": (15.0, 1.0, 20.0)}
    d = {k: design_loops(CARD, 1000.0, 10.0, *fb) for k, fb in paths.items()}
    for k, x in d.items():
        assert x.current_peak_db <= 3.0 + 1e-6 and x.speed_peak_db <= 3.0 + 1e-6, k
        assert x.speed_est_peak_db <= 3.0 + 1e-6, k
        assert x.current_bandwidth_hz == pytest.approx(1000.0, rel=0.01)
    assert d["flux"].speed_bandwidth_hz == pytest.approx(10.0, rel=0.01)
    assert not d["flux"].speed_limited and d["emf"].speed_limited
    assert 6.0 < d["emf"].speed_bandwidth_hz < 8.0


@pytest.mark.parametrize("driving", ["encoder", "emf_measured"])
def test_measured_speed_loop_peaking_within_the_limit(driving):
    """Stepped-sine speed response of the simulated drive (300 rpm, +-60 rpm): the true
    and the estimated speed peak by no more than the 3 dB limit (0.5 dB allowance for the
    measurement) -- before the rule the EMF drive peaked by +10.7 dB at 4 Hz."""
    from fluxdrive.analysis.freqresp import analyse
    from fluxdrive.drive.control import CO_W_FB
    from fluxdrive.drive.plant import TR_WM
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive.experiments.paper import _fr_scenario

    sc = _fr_scenario(driving, [1.5, 3.0, 4.5, 6.0], "speed")
    r = run_scenario(sc, progress=False)
    for resp in (r.truth[:, TR_WM], r.ctrl[:, CO_W_FB]):
        fr = analyse(resp, r.w_ref, r.segments["speed"], sc.machine.ts_s)
        assert max(fr["gain_db"]) <= 3.5, (driving, fr["gain_db"])


def test_paper_2pct_150load_runs_sensorless_on_the_non_ideal_bench():
    """The shipped 2 % / 150 % scenario with its non-ideal bench on (voltage capture,
    current-sampling skew, observer model errors, winding temperature, spatial saturation):
    the drive runs stably sensorless on paper_robust with measured voltages; the literal
    paper observer runs in shadow on the same data."""
    from fluxdrive.analysis.metrics import compute
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
    from fluxdrive.drive.sim import run_scenario

    sc = load_scenario(CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml")
    assert not sc.bench.ideal
    drv = sc.observers[sc.driving]
    assert (drv.variant, drv.voltage_source) == ("paper_robust", "measured")
    assert sc.observers["paper_measured"].variant == "paper"
    m = compute(run_scenario(sc, progress=False))
    assert m["stable"] and abs(m["speed"]["mean_rpm"] - 60.0) < 2.0
    assert m["currents"]["i_q_mean_a"] > 1.3 * sc.machine.rated_current_a
    assert m["observers"]["flux_measured"]["theta_err_peak_deg"] < 30.0
