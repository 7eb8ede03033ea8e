"""Calibration from a lab's own measurements, apart from the figures a model number would decide:
a spin-down (coast-down) for the rig's inertia and friction, and a loaded back-EMF for the
load-dependent 5th and 7th magnet-flux harmonics (the spatial saturation's split).

Spin-down.  With the inverter off the rotor coasts, J dω/dt = −B ω − T_b (B viscous, T_b a
constant brake torque; the electrical torque is zero once the currents have died).  A coast
from the same speed without and with a known dyno brake torque T_b gives J and B without
the motor's torque constant: each coast's deceleration fits dω/dt = −a ω − c, with
a = B/J on both and c = T_b/J on the braked one (c ≈ 0 on the free one), so
J = T_b / (c_braked − c_free) and B = J · a.

Loaded back-EMF.  Under load the magnet flux carries λ·(h5 e^{−j5θ} + h7 e^{j7θ}); its EMF is
jωλ·(e^{jθ} − 5 h5 e^{−j5θ} + 7 h7 e^{j7θ}), in the rotor frame (e^{−jθ}·e)
    e_d = −ωλ (5 h5 + 7 h7) sin 6θ,   e_q = ωλ [1 + (7 h7 − 5 h5) cos 6θ],
so the 6th order of e_d (sine) and of e_q (cosine) against the rotor angle, over e_q's mean,
give 5 h5 + 7 h7 and 7 h7 − 5 h5: the 5th and the 7th apart, with their signs.  The other two
parts (e_d's cosine, e_q's sine) are none of the model's: what the measurement leaves
(deadtime residue of the voltage capture, R̂ and L̂ errors) is read there.  Over several loads
h = h0 + s·x with x = (|i|/I_rated)² gives the per-unit slopes s5, s7 the bench file takes
(spatial_saturation_h5_pu / _h7_pu on top of half of spatial_saturation_h6_pu); h0, the
no-load part, is the machine's static harmonic plus the measurement's residue.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fluxdrive.analysis.metrics import fit_orders


@dataclass(frozen=True)
class Coast:
    """One coast's fit dω/dt = −a ω − c over the samples used (a [1/s], c [rad/s²]), the
    speeds it spans [rad/s] and the RMS of the fit's speed residual [rad/s]."""

    a_per_s: float
    c_rad_s2: float
    w_from_rad_s: float
    w_to_rad_s: float
    residual_rad_s: float


def coast_fit(t_s: np.ndarray, w_rad_s: np.ndarray) -> Coast:
    """Fit ω(t) of a coast with the solution of dω/dt = −a ω − c: ω(t) = (ω0 + c/a)·e^{−a t}
    − c/a, i.e. ω(t) = ω0 − (a ω0 + c)·φ(t) with φ(t) = (1 − e^{−a t})/a.  Linear in (ω0,
    a ω0 + c) for a given a; a is found by a bounded scalar search on the residual, so a
    free coast (c ≈ 0, a small) and a braked one (c dominant, a poorly seen) fit alike."""
    t = np.asarray(t_s, dtype=float) - float(t_s[0])
    w = np.asarray(w_rad_s, dtype=float)

    def solve(a: float) -> tuple[float, np.ndarray]:
        phi = t if a < 1e-9 else -np.expm1(-a * t) / a
        m = np.column_stack([np.ones_like(t), -phi])
        sol, *_ = np.linalg.lstsq(m, w, rcond=None)
        return float(np.sum((m @ sol - w) ** 2)), sol

    # golden-section search for a in [0, 5/T]: a time constant down to a fifth of the coast
    lo, hi = 0.0, 5.0 / max(float(t[-1]), 1e-9)
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = solve(x1)[0], solve(x2)[0]
    for _ in range(80):
        if f1 < f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - g * (hi - lo)
            f1 = solve(x1)[0]
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + g * (hi - lo)
            f2 = solve(x2)[0]
    a = 0.5 * (lo + hi)
    sse, (w0, slope) = solve(a)
    return Coast(
        a_per_s=a,
        c_rad_s2=float(slope - a * w0),
        w_from_rad_s=float(w[0]),
        w_to_rad_s=float(w[-1]),
        residual_rad_s=math.sqrt(sse / len(w)),
    )


@dataclass(frozen=True)
class SpinDown:
    """J [kg m²], viscous B [N m s/rad] and the coasts they come from."""

    inertia_kgm2: float
    viscous_nms: float
    free: Coast
    braked: Coast


def inertia_from_coasts(free: Coast, braked: Coast, brake_nm: float) -> SpinDown:
    """J and B from a free coast and one against a known brake torque `brake_nm` (module
    doc): J = T_b / (c_braked − c_free); B = J · a, a from the free coast (its whole
    deceleration is the viscous part; the braked coast sees a poorly)."""
    j = brake_nm / (braked.c_rad_s2 - free.c_rad_s2)
    return SpinDown(inertia_kgm2=j, viscous_nms=j * free.a_per_s, free=free, braked=braked)


def speed_from_counts(t_s: np.ndarray, counts: np.ndarray, cpr: float, step: int) -> tuple:
    """Mechanical speed [rad/s] from cumulative encoder counts by central differences over
    ±`step` samples (a lab's encoder speed), at the samples it is defined: (t, ω)."""
    c = np.asarray(counts, dtype=float)
    t = np.asarray(t_s, dtype=float)
    w = (c[2 * step :] - c[: -2 * step]) / cpr * 2.0 * math.pi / (t[2 * step :] - t[: -2 * step])
    return t[step:-step], w


@dataclass(frozen=True)
class FluxHarmonics:
    """One loaded back-EMF: h5, h7 per unit of λ (signed, the bench's convention), ωλ [V] (e_q's
    mean), the residue none of the model's (e_d cosine, e_q sine, per unit of ωλ), and the
    load x = mean (|i|/I_rated)²."""

    h5: float
    h7: float
    emf_v: float
    residue_pu: float
    x: float


def flux_harmonics(
    e_alpha: np.ndarray,
    e_beta: np.ndarray,
    theta_e: np.ndarray,
    i_alpha: np.ndarray,
    i_beta: np.ndarray,
    i_rated_a: float,
) -> FluxHarmonics:
    """h5 and h7 from the EMF e (α, β: v − R̂ i − L̂ di/dt over each step) against the rotor's
    electrical angle at the middle of the step (module doc), by the joint fit of orders
    0..20 of e_d and e_q; x from the currents."""
    th = np.asarray(theta_e, dtype=float)
    c, s = np.cos(th), np.sin(th)
    ed = e_alpha * c + e_beta * s
    eq = -e_alpha * s + e_beta * c
    fit = fit_orders(np.column_stack([ed, eq]), th)
    emf = float(np.real(fit.coef[0, 1]))
    c6d, c6q = complex(fit.coef[6, 0]), complex(fit.coef[6, 1])
    # fit_orders: x ≈ Re(c e^{j6θ}) = Re(c) cos 6θ − Im(c) sin 6θ
    s_sum = c6d.imag / emf  # e_d = −ωλ (5 h5 + 7 h7) sin 6θ
    d_diff = c6q.real / emf  # e_q's cos 6θ: ωλ (7 h7 − 5 h5)
    residue = math.hypot(c6d.real, c6q.imag) / abs(emf)
    x = float(np.mean((i_alpha**2 + i_beta**2) / i_rated_a**2))
    return FluxHarmonics(
        h5=(s_sum - d_diff) / 10.0,
        h7=(s_sum + d_diff) / 14.0,
        emf_v=emf,
        residue_pu=residue,
        x=x,
    )


@dataclass(frozen=True)
class SaturationSplit:
    """The slopes s5, s7 of h = h0 + s·x over the loads (per unit of λ at rated current),
    their no-load parts h0, and the largest departure of a load's h from its line."""

    s5: float
    s7: float
    h5_0: float
    h7_0: float
    misfit: float


def saturation_split(points: list[FluxHarmonics]) -> SaturationSplit:
    """Least-squares lines h5(x), h7(x) over the loads measured."""
    x = np.array([p.x for p in points])
    m = np.column_stack([np.ones_like(x), x])
    out, misfit = [], 0.0
    for h in (np.array([p.h5 for p in points]), np.array([p.h7 for p in points])):
        sol, *_ = np.linalg.lstsq(m, h, rcond=None)
        out.append(sol)
        misfit = max(misfit, float(np.max(np.abs(m @ sol - h))))
    (h5_0, s5), (h7_0, s7) = out
    return SaturationSplit(float(s5), float(s7), float(h5_0), float(h7_0), misfit)
