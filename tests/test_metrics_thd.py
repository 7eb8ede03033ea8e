"""THD (orders 2..20) and THD+N (everything but the fundamental) on synthetic signals whose
harmonics and noise are known: THD+N >= THD always, and both equal the known values, also when
the angle is sampled unevenly in time (speed ripple)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.analysis.metrics import thd, thd_n, whole_periods

FS_HZ = 20_000.0
F_E_HZ = 4.0  # 60 rpm on the default card: 4 electrical periods per second
A5, A7, DC, SIGMA = 0.2, 0.1, 0.05, 0.03  # per unit of a unit fundamental


def _signal(ripple_rad: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, 1.0, 1.0 / FS_HZ)
    w = 2 * math.pi * F_E_HZ
    # a 6th-order speed ripple: the rotor crosses some angles faster than others
    theta = w * t + ripple_rad * np.sin(6 * w * t)
    x = (
        np.cos(theta)
        + A5 * np.cos(5 * theta + 0.3)
        + A7 * np.sin(7 * theta)
        + DC
        + SIGMA * np.random.default_rng(seed).standard_normal(len(t))
    )
    sl = whole_periods(theta)
    return x[sl], theta[sl]


@pytest.mark.parametrize("ripple_rad", [0.0, 0.05])
def test_thd_n_at_least_thd_and_both_known(ripple_rad):
    thd_known = math.hypot(A5, A7)  # harmonic amplitudes over the fundamental's
    # RMS of everything but the fundamental over the fundamental's RMS (1/√2):
    # DC² + A5²/2 + A7²/2 + σ² (white noise, fully outside the fundamental)
    thdn_known = math.sqrt(DC**2 + (A5**2 + A7**2) / 2 + SIGMA**2) / (1 / math.sqrt(2))
    for seed in range(3):
        x, th = _signal(ripple_rad, seed)
        a, b = thd(x, th), thd_n(x, th)
        assert b >= a
        assert a == pytest.approx(thd_known, rel=0.01)
        assert b == pytest.approx(thdn_known, rel=0.01)


def test_thd_n_equals_thd_without_noise_or_dc_under_speed_ripple():
    # a pure function of the angle with orders 5 and 7 only: THD+N = THD = hypot(A5, A7) exactly
    # (a time average would leak the fundamental into 5/7 by ≈3× the 0.05 rad ripple)
    t = np.arange(0.0, 1.0, 1.0 / FS_HZ)
    w = 2 * math.pi * F_E_HZ
    theta = w * t + 0.05 * np.sin(6 * w * t)
    x = np.cos(theta) + A5 * np.cos(5 * theta) + A7 * np.cos(7 * theta)
    sl = whole_periods(theta)
    a, b = thd(x[sl], theta[sl]), thd_n(x[sl], theta[sl])
    assert a == pytest.approx(math.hypot(A5, A7), rel=1e-3)
    assert b == pytest.approx(a, rel=1e-3)


def test_one_joint_fit_of_several_signals_gives_each_its_own_numbers():
    # thd_spectra fits every column at once: each column's THD, THD+N and spectrum are what
    # thd(), thd_n() and harmonic_spectrum() give it alone (the known values, per seed)
    from fluxdrive.analysis.metrics import harmonic_spectrum, thd_spectra

    x0, th = _signal(0.05, 0)
    x1, _ = _signal(0.05, 1)
    cols = np.column_stack([x0, 0.5 * x1, np.cos(th) + 0.1 * np.cos(11 * th)])
    fits = thd_spectra(cols, th)
    for j, f in enumerate(fits):
        x = cols[:, j]
        assert f["thd"] == pytest.approx(thd(x, th), rel=1e-9)
        assert f["thd_n"] == pytest.approx(thd_n(x, th), rel=1e-9)
        spec = harmonic_spectrum(x, th)
        assert f["spectrum"] == pytest.approx(spec, rel=1e-9, abs=1e-12)
    assert fits[0]["thd"] == pytest.approx(math.hypot(A5, A7), rel=0.01)
    assert fits[1]["spectrum"][5] == pytest.approx(0.5 * A5, rel=0.02)
    assert fits[2]["thd"] == pytest.approx(0.1, rel=1e-6)  # noise-free: exact
