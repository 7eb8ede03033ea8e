"""The firmware's inline math (firmware/include/fd_math.h) against libm.

fd_sincosf replaces newlib's sinf/cosf in the period interrupt (a polynomial after a
Cody-Waite reduction): its stated bound FD_SINCOS_ERR_MAX must hold against the exact
sine/cosine (numpy's double precision) over its whole range |x| <= FD_SINCOS_X_MAX, densely
near the interrupt's angles [-2 pi, 2 pi] and at the quadrant boundaries; beyond the range
and for NaN/Inf it answers what libm's sinf/cosf answer."""

from __future__ import annotations

import ctypes
import re

import numpy as np
import pytest
from fluxdrive.can import firmware as fw

HEADER = (fw.FIRMWARE_DIR / "include" / "fd_math.h").read_text()
ERR_MAX = float(re.search(r"#define FD_SINCOS_ERR_MAX ([0-9.e+-]+)f", HEADER).group(1))
X_MAX = float(re.search(r"#define FD_SINCOS_X_MAX ([0-9.e+-]+)f", HEADER).group(1))


@pytest.fixture(scope="module")
def sincos():
    lib = fw.load_library()
    fn = lib.fd_sincos
    fn.restype = None
    fn.argtypes = [ctypes.c_float, ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_float)]
    s, c = ctypes.c_float(), ctypes.c_float()

    def call(x: float) -> tuple[float, float]:
        fn(x, ctypes.byref(s), ctypes.byref(c))
        return s.value, c.value

    return call


def _worst(sincos, xs: np.ndarray) -> float:
    xs = xs.astype(np.float32)
    got = np.array([sincos(float(x)) for x in xs])
    x64 = xs.astype(np.float64)
    return float(
        max(np.max(np.abs(got[:, 0] - np.sin(x64))), np.max(np.abs(got[:, 1] - np.cos(x64))))
    )


def test_sincos_within_its_stated_bound(sincos):
    rng = np.random.default_rng(29)
    near = np.linspace(-2 * np.pi, 2 * np.pi, 40001)
    quadrants = np.array([k * np.pi / 4 + d for k in range(-16, 17) for d in (-1e-6, 0.0, 1e-6)])
    wide = rng.uniform(-X_MAX, X_MAX, 20000)
    worst = max(_worst(sincos, xs) for xs in (near, quadrants, wide))
    print(f"fd_sincosf: largest absolute error {worst:.3g} (stated {ERR_MAX:.3g})")
    assert worst <= ERR_MAX
    # and not a loose bound: newlib/glibc sinf (about 0.5 ulp) is within 6e-8
    assert worst > 0.25 * ERR_MAX


def test_sincos_outside_its_range_is_libm(sincos):
    for x in (X_MAX * 1.5, -1.0e6, 3.0e7):
        s, c = sincos(x)
        x32 = float(np.float32(x))
        assert s == pytest.approx(np.sin(x32), abs=1e-6) and c == pytest.approx(
            np.cos(x32), abs=1e-6
        )
    for x in (float("nan"), float("inf"), float("-inf")):
        s, c = sincos(x)
        assert np.isnan(s) and np.isnan(c)
