"""The one Clarke/Park implementation (amplitude-invariant), plus angle helpers."""

from __future__ import annotations

import math

from numba import njit

SQRT3 = math.sqrt(3.0)
TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def clarke(a: float, b: float, c: float) -> tuple[float, float]:
    """abc -> alpha-beta, amplitude invariant; the common mode (a+b+c)/3 drops out."""
    return (2.0 * a - b - c) / 3.0, (b - c) / SQRT3


@njit(cache=True, inline="always")
def inv_clarke(alpha: float, beta: float) -> tuple[float, float, float]:
    """alpha-beta -> abc (zero common mode)."""
    half_b = 0.5 * SQRT3 * beta
    return alpha, -0.5 * alpha + half_b, -0.5 * alpha - half_b


@njit(cache=True, inline="always")
def park(alpha: float, beta: float, cos_t: float, sin_t: float) -> tuple[float, float]:
    """Stationary -> rotor frame (d along the magnet flux)."""
    return alpha * cos_t + beta * sin_t, -alpha * sin_t + beta * cos_t


@njit(cache=True, inline="always")
def inv_park(d: float, q: float, cos_t: float, sin_t: float) -> tuple[float, float]:
    """Rotor -> stationary frame."""
    return d * cos_t - q * sin_t, d * sin_t + q * cos_t


@njit(cache=True, inline="always")
def wrap_angle(x: float) -> float:
    """Wrap an angle to [-pi, pi): (x + pi) mod 2 pi - pi.  An angle already in range (the
    usual case: one step of an angle kept wrapped) skips the floating modulo, which returns
    y itself for y in [0, 2 pi), so the result is the same to the bit."""
    y = x + math.pi
    if 0.0 <= y < TWO_PI:
        return y - math.pi
    return y % TWO_PI - math.pi


@njit(cache=True, inline="always")
def line_to_phase(v_ab: float, v_bc: float, v_ca: float) -> tuple[float, float, float]:
    """Phase voltages (to the floating neutral) from line-to-line voltages (paper Sec. III-B)."""
    return (v_ab - v_ca) / 3.0, (v_bc - v_ab) / 3.0, (v_ca - v_bc) / 3.0
