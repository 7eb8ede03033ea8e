"""The shared discrete-time building blocks: first-order filter discretisation, PI, PLL, RNG.

One discretisation for every first-order filter in the project: the exact (ZOH) pole
a = exp(-w_c Ts).  The leaky integrator 1/(s + w_c) and the low-pass w_c/(s + w_c)
differ only in their input gain.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fluxdrive.core.transforms import wrap_angle


# ---------------------------------------------------------------- sign
@njit(cache=True, inline="always")
def sign(x: float) -> float:
    """+1, -1, or 0 at exactly zero (numpy's sign for one float, inlined)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0


# ---------------------------------------------------------------- first-order filters
@njit(cache=True, inline="always")
def pole(cutoff_rad_s: float, ts_s: float) -> float:
    """Discrete pole a = exp(-w_c Ts) of a first-order section."""
    return math.exp(-cutoff_rad_s * ts_s)


@njit(cache=True, inline="always")
def lowpass_step(y: float, x: float, a: float) -> float:
    """Unity-DC-gain low-pass w_c/(s+w_c): y <- a y + (1-a) x."""
    return a * y + (1.0 - a) * x


@njit(cache=True, inline="always")
def leaky_integrator_step(y: float, x: float, a: float, cutoff_rad_s: float, ts_s: float) -> float:
    """1/(s + w_c) (= integrator followed by HPF s/(s+w_c)); pure integrator when w_c = 0."""
    if cutoff_rad_s <= 0.0:
        return y + ts_s * x
    return a * y + (1.0 - a) / cutoff_rad_s * x


# ---------------------------------------------------------------- PI controller
@njit(cache=True, inline="always")
def pi_output(kp: float, integ: float, err: float) -> float:
    """Unsaturated PI output (integral state already in output units)."""
    return kp * err + integ


@njit(cache=True, inline="always")
def pi_update(
    integ: float, ki: float, ts_s: float, err: float, out_unsat: float, out_sat: float
) -> float:
    """Integrate and back-calculate: the integrator absorbs the part the limiter cut off,
    so it never winds up beyond what the actuator realised."""
    return integ + ki * ts_s * err + (out_sat - out_unsat)


# ---------------------------------------------------------------- PLL
def pll_gains(bandwidth_hz: float, damping: float) -> tuple[float, float]:
    """Type-2 PLL on sin(angle error): Kp = 2 zeta w_n, Ki = w_n^2 (docs/engine.md, PLL)."""
    wn = 2.0 * math.pi * bandwidth_hz
    return 2.0 * damping * wn, wn * wn


@njit(cache=True, inline="always")
def pll_step(
    theta: float, integ: float, err: float, kp: float, ki: float, ts_s: float
) -> tuple[float, float, float]:
    """One PLL step.  `theta` is the estimate for this sample (used to form `err`).
    Returns (omega for this sample, new integrator, theta predicted for the next sample)."""
    integ = integ + ki * ts_s * err
    omega = kp * err + integ
    return omega, integ, wrap_angle(theta + ts_s * omega)


# ---------------------------------------------------------------- deterministic RNG
# xorshift64* in a uint64 cell + Box-Muller; independent of numpy's/numba's global
# generators, so a plant run in a node and in the runner draw identical numbers.
_M = np.uint64(2685821657736338717)
_S12 = np.uint64(12)
_S25 = np.uint64(25)
_S27 = np.uint64(27)
_S11 = np.uint64(11)


def rng_new(seed: int) -> np.ndarray:
    """RNG state cell from a seed (splitmix-style scramble so small seeds differ well)."""
    z = (int(seed) + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    z ^= z >> 31
    return np.array([z or 1], dtype=np.uint64)


@njit(cache=True)
def rng_uniform(cell: np.ndarray) -> float:
    """Uniform in (0, 1)."""
    x = cell[0]
    x ^= x >> _S12
    x ^= x << _S25
    x ^= x >> _S27
    cell[0] = x
    return (float((x * _M) >> _S11) + 0.5) / 9007199254740992.0


@njit(cache=True)
def rng_normal(cell: np.ndarray) -> float:
    """Standard normal (Box-Muller, one of the pair)."""
    u1 = rng_uniform(cell)
    u2 = rng_uniform(cell)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


# ---------------------------------------------------------------- profiles
@njit(cache=True)
def pwl(ts: np.ndarray, ys: np.ndarray, t: float) -> float:
    """Piecewise-linear profile value at t (held constant outside the breakpoints)."""
    n = ts.shape[0]
    if t <= ts[0]:
        return ys[0]
    if t >= ts[n - 1]:
        return ys[n - 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ts[mid] <= t:
            lo = mid
        else:
            hi = mid
    span = ts[hi] - ts[lo]
    if span <= 0.0:
        return ys[hi]
    return ys[lo] + (ys[hi] - ys[lo]) * (t - ts[lo]) / span
