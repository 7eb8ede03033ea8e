"""fluxdrive: position-sensorless SPM drive testbed (algorithms only, no ROS imports).

Every per-sample algorithm is a numba-compiled kernel working on small float64
state/parameter arrays (MCU style), so the same compiled code runs inside the
in-process runner's loop, inside the ROS nodes one sample at a time, and in
bag replay, and gives bit-identical numbers in all three.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__version__ = "0.1.0"


# The packages that hold numba kernels and everything they call: by the layer rule
# (CONTRIBUTING.md) drive imports only core, so their sources are all a kernel can depend on.
# tests/test_kernel_cache.py fails when a kernel appears anywhere else.
KERNEL_PACKAGES = ("core", "drive")


def kernel_sources_hash() -> str:
    """sha1 over the sources of KERNEL_PACKAGES (names and bytes): the numba cache key."""
    here = Path(__file__).resolve().parent
    h = hashlib.sha1()
    for pkg in KERNEL_PACKAGES:
        for f in sorted((here / pkg).rglob("*.py")):
            h.update(str(f.relative_to(here)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def _numba_cache_dir() -> None:
    """Key numba's on-disk cache on the kernel sources.  numba only checks the file of the
    cached function itself, so a changed callee in another module would otherwise run
    stale machine code; an edit outside the kernels' packages (an experiment, the CLI)
    keeps the cache."""
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    key = kernel_sources_hash()
    from fluxdrive.core.paths import ROOT

    root = ROOT / ".ws" / "numba_cache"  # the checkout's work folder, else the user's cache
    try:
        root.mkdir(parents=True, exist_ok=True)
        test = root / ".w"
        test.touch()
    except OSError:
        root = Path.home() / ".cache" / "fluxdrive" / "numba"
    os.environ["NUMBA_CACHE_DIR"] = str(root / key[:16])


_numba_cache_dir()
