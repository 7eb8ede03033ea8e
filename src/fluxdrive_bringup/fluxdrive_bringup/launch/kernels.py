"""Kernels compiled before a graph starts (fluxdrive.drive.warm), so that no node compiles
on its first frame: the launcher calls `warm_for_graph` before it starts the processes.

Once per engine version: numba's disk cache is keyed on the engine's sources
(NUMBA_CACHE_DIR, set by fluxdrive/__init__.py), and a marker file in that cache directory
says the graph's kernels are in it, so later starts skip the step (the processes load the
machine code from the cache in a fraction of a second each)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable
from pathlib import Path

MARKER = "graph_kernels.json"
KERNEL_NODES = ("plant", "observer", "controller")


def warm_for_graph(scenarios: Iterable[object], say: Callable[[str], None]) -> dict | None:
    """Compile (or load) the kernels of a graph whose plant, observers or controller run
    `scenarios` (their `scenario` parameters; the first one set counts), with progress
    lines through `say`, unless the cache holds them already; None when there was nothing
    to do."""
    cache = os.environ.get("NUMBA_CACHE_DIR")
    sp = next((str(s) for s in scenarios if s), None)
    if not cache or sp is None:
        return None
    marker = Path(cache) / MARKER
    if marker.exists():
        return None
    from fluxdrive.core.machine import ConfigError
    from fluxdrive.drive.scenario import load_scenario, scenario_path
    from fluxdrive.drive.warm import warm_graph_kernels

    try:
        sc = load_scenario(scenario_path(sp))
    except (ConfigError, OSError, ValueError):
        return None  # the node says what is wrong with it, in one line
    res = warm_graph_kernels(sc, say)
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text(json.dumps(res))
    except OSError:
        pass  # no marker: the next start loads the kernels again (quick)
    return res
