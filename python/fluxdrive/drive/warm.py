"""The kernels a drive's graph nodes call from Python, compiled (or loaded from numba's disk
cache) in one go before the graph starts.

A node calls its kernels per sample (`plant_advance`, `observer_step`, `controller_step`, ...);
numba compiles each on its first call.  Left to the nodes, that first call comes with the
first frame: after an engine edit (the cache is keyed on the engine's sources, see
fluxdrive/__init__.py) a composed graph sat for 10-14 s at "0.00/11.00 s simulated" without a
word.  `warm_graph_kernels` makes every one of those calls once, with the argument types the
nodes use (built by the same engine objects: DriveSetup, the observer configuration, the
controller's parameter row), saying which kernel it is at; the machine code lands in the disk
cache, and the graph's processes load it from there.
"""

from __future__ import annotations

import fcntl
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from fluxdrive.drive.control import (
    CO_N,
    RF_N,
    controller_clear_fault,
    controller_reset,
    controller_step,
    host_reference_step,
)
from fluxdrive.drive.observers import (
    ES_N,
    OS_N,
    block_out_of_range,
    frame_limits,
    frame_out_of_range,
    observer_reset,
    observer_run,
    observer_step,
)
from fluxdrive.drive.plant import FR_N, TR_N, plant_advance, plant_initial_frame
from fluxdrive.drive.sim import DriveSetup

Say = Callable[[str], None]
# every kernel a graph node calls from Python (numba dispatchers)
KERNELS = (
    plant_initial_frame,
    plant_advance,
    observer_reset,
    observer_step,
    observer_run,
    frame_out_of_range,
    block_out_of_range,
    controller_reset,
    controller_step,
    controller_clear_fault,
    host_reference_step,
)


def direct(kernel, *args) -> Callable:
    """`kernel`'s machine code for arguments of the types of `args`, callable without numba's
    dispatch (which works out the type of every argument at every call: 0.2-0.5 us for the
    kernels a node calls per sample).  The same compiled code as `kernel(*args)` (compiled,
    or loaded from the disk cache, now; nothing is run).  Only for a caller that passes
    arguments of these very types at every call -- the same arrays, or arrays made the same
    way (numba checks an array's dtype, not its dimensions or memory layout)."""
    from numba import typeof

    return kernel.compile(tuple(typeof(a) for a in args))  # type: ignore[attr-defined]


def graph_kernel_calls(sc) -> list[tuple[object, tuple]]:
    """(kernel, arguments) of every kernel the plant, observer and controller nodes call
    from Python, with arguments of the types those nodes pass (scenario `sc`)."""
    ds = DriveSetup(sc)
    pst, rng = ds.new_plant()
    mp = ds.mp.copy()
    frame, truth = np.zeros(FR_N), np.zeros(TR_N)
    duty = np.array([0.5, 0.5, 0.5])
    first = next(iter(sc.observers.values()))
    op = first.resolved(sc.machine).to_params(sc.machine)
    ost, est = np.zeros(OS_N), np.zeros(ES_N)
    cs, cp, out, ref = ds.new_controller(), ds.cp.copy(), np.zeros(CO_N), np.zeros(RF_N)
    load = (ds.load_t, ds.load_y, ds.load_cfg)
    return [
        (plant_initial_frame, (pst, mp, rng, frame, truth)),
        (plant_advance, (pst, mp, rng, duty, False, *load, frame, truth)),
        (observer_reset, (ost,)),
        (observer_step, (ost, op, frame, est)),
        (observer_run, (ost, op, np.zeros((2, FR_N)), np.zeros((2, ES_N)))),  # shadows' blocks
        (frame_out_of_range, (frame, frame_limits(sc.machine))),
        (block_out_of_range, (np.zeros((2, FR_N)), frame_limits(sc.machine))),
        (controller_reset, (cs,)),
        (controller_step, (cs, cp, frame, est, 0.0, 0.0, out)),
        (controller_clear_fault, (cs,)),
        (host_reference_step, (cs, cp, frame, est, 0.0, 0.0, out, ref)),
    ]


@contextmanager
def cache_lock() -> Iterator[None]:
    """Hold numba's disk cache (NUMBA_CACHE_DIR) alone while compiling into it: processes
    warming at once (the test suite's xdist workers, two launchers) take turns, and the later
    ones load what the first compiled instead of compiling it again beside it."""
    cache = os.environ.get("NUMBA_CACHE_DIR")
    if not cache:
        yield
        return
    Path(cache).mkdir(parents=True, exist_ok=True)
    with open(Path(cache) / ".warm.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        yield


def warm_graph_kernels(sc, say: Say) -> dict:
    """Compile or load every kernel of `graph_kernel_calls`, one progress line each
    ("compiling kernels ... 3/9 observer_step"), then one summary line.  Returns
    {"kernels": n, "compiled": n compiled now, "cached": n loaded from the disk cache,
    "seconds": wall time}."""

    def counts(kernel) -> tuple[int, int]:  # a numba dispatcher's cache statistics
        st = kernel.stats
        return sum(st.cache_misses.values()), sum(st.cache_hits.values())

    t0 = time.perf_counter()
    with cache_lock():
        before = {k: counts(k) for k in KERNELS}  # setting up may call some already
        calls = graph_kernel_calls(sc)
        for i, (kernel, args) in enumerate(calls, 1):
            say(f"compiling kernels ... {i}/{len(calls)} {kernel.__name__}")  # type: ignore[attr-defined]
            kernel(*args)  # type: ignore[operator]
    after = {k: counts(k) for k in KERNELS}
    compiled = sum(after[k][0] > before[k][0] for k in KERNELS)
    cached = sum(after[k][1] > before[k][1] for k in KERNELS)
    dt = time.perf_counter() - t0
    say(
        f"kernels ready: {len(calls)} in {dt:.1f} s ({compiled} compiled, {cached} from the "
        f"disk cache)"
    )
    return {"kernels": len(calls), "compiled": compiled, "cached": cached, "seconds": dt}
