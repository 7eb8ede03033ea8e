"""The lab's calibration measurements (fluxdrive.analysis.calibration): a spin-down's J and
friction from two coasts, the loaded back-EMF's 5th and 7th; on signals that follow the
equations with known numbers, and the spin-down once on the engine."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from fluxdrive.analysis.calibration import (
    FluxHarmonics,
    coast_fit,
    flux_harmonics,
    inertia_from_coasts,
    saturation_split,
    speed_from_counts,
)

J, B = 1.96e-3, 1.0e-4  # kg m^2, N m s/rad


def _coast(t, w0, brake_nm):
    """ω(t) of J dω/dt = −B ω − T_b from ω0: (ω0 + T_b/B) e^{−t B/J} − T_b/B."""
    return (w0 + brake_nm / B) * np.exp(-t * B / J) - brake_nm / B


def test_two_coasts_give_inertia_and_friction():
    """A free coast and one against a known brake torque give J and B (not J/B alone), from
    encoder counts as the lab has them (10 000 counts/rev, speed by differences)."""
    t = np.arange(0.0, 3.0, 1e-3)
    free = coast_fit(t, _coast(t, 157.0, 0.0))
    assert free.a_per_s == pytest.approx(B / J, rel=1e-4) and abs(free.c_rad_s2) < 1e-3
    tb = t[t < 1.0]
    cpr = 10_000.0
    theta = np.cumsum(_coast(tb, 157.0, 0.254)) * 1e-3  # rad, rectangle rule
    counts = np.floor(theta / (2 * math.pi) * cpr)
    ts, w = speed_from_counts(tb, counts, cpr, 5)
    braked = coast_fit(ts, w)
    sd = inertia_from_coasts(free, braked, 0.254)
    assert sd.inertia_kgm2 == pytest.approx(J, rel=5e-3)
    assert sd.viscous_nms == pytest.approx(B, rel=5e-3)


def test_loaded_back_emf_gives_the_5th_and_7th_apart():
    """EMF jωλ(e^{jθ} − 5 h5 e^{−j5θ} + 7 h7 e^{j7θ}) plus a residue in the quadrature parts
    and seeded noise: h5, h7 recovered with their signs within 1 %, the residue read apart."""
    rng = np.random.default_rng(7)
    th = np.linspace(0.0, 40 * 2 * math.pi, 8_000)  # 40 electrical periods
    w_lam, h5, h7 = 14.8, 0.004, -0.002
    e = 1j * w_lam * (np.exp(1j * th) - 5 * h5 * np.exp(-5j * th) + 7 * h7 * np.exp(7j * th))
    e = e + 0.01 * w_lam * np.exp(1j * th) * np.cos(6 * th)  # a d-axis cos 6θ: no model's
    e = e + rng.normal(0.0, 0.05, th.size) + 1j * rng.normal(0.0, 0.05, th.size)
    i = 9.0 * 1j * np.exp(1j * th)  # rated q current
    f = flux_harmonics(e.real, e.imag, th, i.real, i.imag, 9.0)
    assert f.h5 == pytest.approx(h5, rel=1e-2) and f.h7 == pytest.approx(h7, rel=1e-2)
    assert f.emf_v == pytest.approx(w_lam, rel=1e-3) and f.x == pytest.approx(1.0, rel=1e-9)
    assert f.residue_pu == pytest.approx(0.01, rel=2e-2)


def test_saturation_slopes_over_the_loads():
    """h = h0 + s x over the loads: the slopes are the bench's per-unit numbers."""
    pts = [
        FluxHarmonics(h5=1e-4 + 0.002 * x, h7=-5e-5 + 0.003 * x, emf_v=14.8, residue_pu=0, x=x)
        for x in (0.0, 0.25, 1.0, 2.25)
    ]
    s = saturation_split(pts)
    assert s.s5 == pytest.approx(0.002, rel=1e-9) and s.s7 == pytest.approx(0.003, rel=1e-9)
    assert s.h5_0 == pytest.approx(1e-4, rel=1e-9) and s.misfit < 1e-12


def test_spin_down_on_the_engine_returns_the_rigs_inertia(tmp_path: Path):
    """The experiment's spin-down on the engine (the paper rig, its bench, shortened coasts):
    J within 1 % of the rig's, the friction (half a second of a 20 s time constant) within
    10 % -- the procedure recovers what the rig was built with."""
    from fluxdrive.experiments import calib
    from fluxdrive.experiments.common import Ctx

    ctx = Ctx(out=tmp_path, quick=True, echo=False)
    free = calib._rig(ctx, duration_s=1.3, load_pu=0.0, steady_window_s=[0.6, 0.8])
    braked = calib._rig(
        ctx,
        duration_s=1.2,
        load_pu=[[0.0, 0.0], [0.6, 0.0], [0.65, calib.BRAKE_PU]],
        steady_window_s=[0.6, 0.8],
    )
    runs = [calib._coast_job((sc, 0.8)) for sc in (free, braked)]
    f, _, _ = calib._coast(runs[0], 0.0)
    b, tb, _ = calib._coast(runs[1], calib.BRAKED_FLOOR)
    assert tb == pytest.approx(calib.BRAKE_PU * free.machine.rated_torque_nm, rel=1e-6)
    sd = inertia_from_coasts(f, b, tb)
    assert sd.inertia_kgm2 == pytest.approx(free.machine.inertia_kgm2, rel=1e-2)
    assert sd.viscous_nms == pytest.approx(free.machine.viscous_nms, rel=0.1)


def test_noise_limited_bandwidth_is_where_the_noise_crosses_the_limit():
    """Noise growing as bandwidth² crosses a limit at the bandwidth the power law gives
    (log-log interpolation is exact for it); settings lost below the first that ran are
    skipped, a setting lost above it ends the sweep, none past the limit: the highest."""
    from fluxdrive.experiments.bandwidth_noise import noise_limited_bandwidth

    bws = [2.0, 4.0, 8.0, 16.0]
    noise = [1e-3 * (b / 2.0) ** 2 for b in bws]  # 1, 4, 16, 64 mA
    assert noise_limited_bandwidth(bws, noise, 0.01) == pytest.approx(2.0 * math.sqrt(10.0))
    assert noise_limited_bandwidth(bws, [math.nan, *noise[1:]], 0.01) == pytest.approx(
        2.0 * math.sqrt(10.0)
    )
    assert noise_limited_bandwidth(bws, [*noise[:2], math.nan, noise[3]], 0.01) == 4.0
    assert noise_limited_bandwidth(bws, noise, 1.0) == 16.0
    assert math.isnan(noise_limited_bandwidth(bws, noise, 1e-4))


def test_lowest_bandwidth_within_a_falling_noise():
    """Noise falling as 1/bandwidth² comes within a limit at the bandwidth the power law
    gives; never within: nan; within from the first setting: that setting."""
    from fluxdrive.experiments.bandwidth_noise import lowest_bandwidth_within

    bws = [2.0, 4.0, 8.0, 16.0]
    noise = [4.0 * (2.0 / b) ** 2 for b in bws]  # 4, 1, 0.25, 0.0625 rpm
    assert lowest_bandwidth_within(bws, noise, 2.0) == pytest.approx(2.0 * math.sqrt(2.0))
    assert lowest_bandwidth_within(bws, [math.nan, *noise[1:]], 2.0) == 4.0
    assert lowest_bandwidth_within(bws, noise, 10.0) == 2.0
    assert math.isnan(lowest_bandwidth_within(bws, noise, 0.01))
