"""Smoke test of the CAN throughput benchmark (small, fast); the figures themselves come from
`./fluxdrive benchmark can`."""

from __future__ import annotations

import sys
from pathlib import Path

try:
    import fluxdrive.can.benchmark  # noqa: F401
except ImportError:  # not installed: use the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))

from fluxdrive.can.benchmark import measure_decode_rates, run_can_benchmark


def test_benchmark_smoke_no_drops():
    res = run_can_benchmark(3000, decode_rates=False, progress=False)
    assert res["decoded"] == 3000 and res["dropped"] == 0
    assert res["malformed"] == 0 and res["seq_lost"] == 0 and not res["listener_errors"]
    assert res["frames_per_s"] > 0


def test_decode_rates_measured():
    # the speed-up itself is a figure of `./fluxdrive benchmark can` (numpy_speedup), not
    # something a unit test on a shared machine can assert
    r = measure_decode_rates(n_numpy=2_000, n_cantools=200)
    assert set(r) >= {"cantools_decode_frames_per_s", "numpy_decode_frames_per_s", "numpy_speedup"}
    assert all(v > 0 and v < float("inf") for v in r.values())
