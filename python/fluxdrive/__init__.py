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


def _numba_cache_dir() -> None:
    """Key numba's on-disk cache on the package sources.  numba only checks the file of the
    cached function itself, so a changed callee in another module would otherwise run
    stale machine code."""
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    here = Path(__file__).resolve().parent
    h = hashlib.sha1()
    for f in sorted(here.rglob("*.py")):  # every kernel source, in every subpackage
        if f.parent.name == "study":  # orchestration only, no kernels: edits need no rebuild
            continue
        h.update(str(f.relative_to(here)).encode())
        h.update(f.read_bytes())
    from fluxdrive.core.paths import ROOT

    root = ROOT / ".ws" / "numba_cache"  # the checkout's work folder, else the user's cache
    try:
        root.mkdir(parents=True, exist_ok=True)
        test = root / ".w"
        test.touch()
    except OSError:
        root = Path.home() / ".cache" / "fluxdrive" / "numba"
    os.environ["NUMBA_CACHE_DIR"] = str(root / h.hexdigest()[:16])


_numba_cache_dir()
