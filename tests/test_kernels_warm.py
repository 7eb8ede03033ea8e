"""Kernels compiled before a graph starts: the launcher's warm-up step names each kernel as
it goes and is skipped once the engine version's cache holds them (fluxdrive.drive.warm,
fluxdrive_bringup.launch.kernels)."""

from __future__ import annotations

import re

import pytest
from fluxdrive.drive.scenario import load_scenario, scenario_path


def test_warm_names_every_kernel_in_order():
    from fluxdrive.drive.warm import KERNELS, warm_graph_kernels

    lines: list[str] = []
    res = warm_graph_kernels(load_scenario(scenario_path("paper_2pct_150load")), lines.append)
    n = len(KERNELS)
    assert res["kernels"] == n
    steps = [re.fullmatch(r"compiling kernels \.\.\. (\d+)/(\d+) (\w+)", ln) for ln in lines[:-1]]
    assert all(steps), lines
    assert [(int(m[1]), int(m[2])) for m in steps] == [(i, n) for i in range(1, n + 1)]
    assert [m[3] for m in steps] == [k.__name__ for k in KERNELS]
    assert lines[-1].startswith(f"kernels ready: {n} in ")
    # every kernel now has machine code for the nodes' argument types
    assert all(len(k.overloads) >= 1 for k in KERNELS)


def test_launcher_warms_once_per_engine_version(tmp_path, monkeypatch):
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive_bringup.launch.kernels import MARKER, warm_for_graph

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    (tmp_path / MARKER).write_text("{}")  # this cache holds them: nothing to do, no line
    said: list[str] = []
    assert warm_for_graph(["paper_2pct_150load"], said.append) is None and said == []
    # a graph without a plant, observer or controller (a bench bridge alone): nothing either
    (tmp_path / MARKER).unlink()
    assert warm_for_graph([None], said.append) is None and said == []
