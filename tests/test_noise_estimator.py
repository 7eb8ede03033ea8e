"""The one noise estimator (analysis.metrics.fit_orders / noise_rms): a joint least-squares fit
of orders 0..20 against the measured rotor angle.  On synthetic θ̃ with known harmonics and
white noise, under a strong 6th-order speed ripple (the rotor hunting as at 2 % speed, 150 %
load), it recovers every harmonic's amplitude and the noise RMS within 2 %; one projection per
order does not (what the joint fit replaced)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.analysis.metrics import fit_orders, harmonic_spectrum, noise_rms, whole_periods

FS_HZ = 20_000.0
F_E_HZ = 4.0  # 60 rpm on the default card
# order -> amplitude [deg]: an offset, the 1st (an angle offset's trace), the deadtime 6th,
# the 12th, and orders that leak into their neighbours under ripple
ORDERS = {0: 1.5, 1: 0.8, 2: 0.5, 5: 0.6, 6: 3.0, 7: 0.5, 12: 0.5, 18: 0.5}
SIGMA_DEG = 0.3


def _case(ripple_pu: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """θ̃ [deg] and the unwrapped rotor angle: the speed swings ±ripple_pu at the 6th order
    (0.2: 24 rpm p-p at 60 rpm)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 2.0, 1.0 / FS_HZ)
    w = 2 * math.pi * F_E_HZ
    # dθ/dt = w (1 + r cos 6wt)  ->  θ = w t + r/6 sin 6wt
    theta = w * t + ripple_pu / 6.0 * np.sin(6 * w * t)
    phase = rng.uniform(0, 2 * math.pi, len(ORDERS))
    x = sum(
        a * (np.cos(n * theta + p) if n else 1.0)
        for (n, a), p in zip(ORDERS.items(), phase, strict=True)
    )
    x = x + SIGMA_DEG * rng.standard_normal(len(t))
    return np.asarray(x, dtype=float), theta


@pytest.mark.parametrize("ripple_pu", [0.0, 0.2, 0.4])
def test_joint_fit_recovers_harmonics_and_noise_within_2_percent(ripple_pu):
    for seed in (1, 2):
        x, th = _case(ripple_pu, seed)
        sl = whole_periods(th)
        fit = fit_orders(x[sl], th[sl])
        for n, a in ORDERS.items():
            assert fit.amplitude(n) == pytest.approx(a, rel=0.02), (n, seed)
        assert fit.noise_rms == pytest.approx(SIGMA_DEG, rel=0.02)
        assert noise_rms(x, th) == pytest.approx(SIGMA_DEG, rel=0.02)
        # the spectrum the scope and replay draw is the same fit's
        spec = harmonic_spectrum(x[sl], th[sl], range(1, 21))
        assert spec[6] == pytest.approx(fit.amplitude(6), rel=1e-9)


def test_one_order_at_a_time_leaves_harmonic_power_under_ripple():
    """Why the joint fit: under 40 % speed ripple subtracting angle-weighted projections one
    order at a time (the former estimator) overstates the noise, since e^{jnθ} are not
    orthogonal over the samples; the joint fit does not."""
    x, th = _case(0.4, 1)
    sl = whole_periods(th)
    xs, ths = x[sl], th[sl]
    d = np.abs(np.diff(ths))
    w = np.append(d, d[-1]) / np.sum(np.append(d, d[-1]))  # the angle weights it used
    y = xs - np.mean(xs)
    for n in range(1, 21):
        c = 2.0 * np.sum(w * y * np.exp(-1j * n * ths))
        y = y - np.real(c * np.exp(1j * n * ths))
    one_at_a_time = float(np.sqrt(np.mean(y**2)))
    assert one_at_a_time > 1.05 * SIGMA_DEG
    assert noise_rms(x, th) == pytest.approx(SIGMA_DEG, rel=0.02)


def test_signals_fitted_together_equal_alone_and_nan_stays_in_its_column():
    x, th = _case(0.2, 4)
    both = fit_orders(np.column_stack([x, 2 * x, np.full_like(x, np.nan)]), th)
    alone = fit_orders(x, th)
    assert np.allclose(both.coef[:, 0], alone.coef)
    assert np.allclose(both.coef[:, 1], 2 * alone.coef)
    assert np.all(np.isnan(both.coef[:, 2]))
