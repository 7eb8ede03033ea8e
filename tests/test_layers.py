"""Layers that hold: the import graph of python/ and src/ (every import statement, those inside
functions included) against the table of allowed imports between subpackages, and no import
cycle between modules.

    core  <-  drive  <-  {analysis, can <- io}  <-  replay  <-  study  <-  experiments  <-  cli
                                                                           <-  ROS packages (src/)

and, inside fluxdrive_bringup, its jobs: {record, inspect, replay} <- {view, launch} <- measure.

A package may import its own modules and anything the table lists for it; nothing else."""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

ENGINE_LOW = {"fluxdrive", "fluxdrive.core"}
# subpackage -> the subpackages it may import (its own modules always)
ALLOWED: dict[str, set[str]] = {
    "fluxdrive": {"fluxdrive.core"},  # the package's __init__: version, paths
    "fluxdrive.core": set(),
    "fluxdrive.drive": {"fluxdrive.core"},
    "fluxdrive.analysis": {"fluxdrive.core", "fluxdrive.drive"},
    "fluxdrive.can": {"fluxdrive.core", "fluxdrive.drive"},
    # a capture (can.canlog) becomes a bag here
    "fluxdrive.io": {"fluxdrive.core", "fluxdrive.drive", "fluxdrive.can"},
}
_MID = {"fluxdrive.core", "fluxdrive.drive", "fluxdrive.analysis", "fluxdrive.io", "fluxdrive.can"}
ALLOWED["fluxdrive.replay"] = _MID | {"fluxdrive"}
ALLOWED["fluxdrive.study"] = ALLOWED["fluxdrive.replay"] | {"fluxdrive.replay"}
ALLOWED["fluxdrive.experiments"] = ALLOWED["fluxdrive.study"] | {"fluxdrive.study"}
ALLOWED["fluxdrive.cli"] = ALLOWED["fluxdrive.experiments"] | {"fluxdrive.experiments"}
ENGINE = set(ALLOWED)
# ROS packages: the shared ROS layer over the whole engine, nodes and tools over that
ALLOWED["fluxdrive_ros"] = ENGINE
for _pkg in ("spm_plant_sim", "flux_observer_node", "foc_controller_node", "bench_bridge"):
    ALLOWED[_pkg] = ENGINE | {"fluxdrive_ros"}
# fluxdrive_bringup by job: record, inspect and replay stand alone; view and launch look into a
# running graph (inspect); launch also starts recorders (record); measure runs graphs (launch)
_ROS = ENGINE | {"fluxdrive_ros"}
_JOB = {job: f"fluxdrive_bringup.{job}" for job in ("launch", "record", "inspect", "view")}
ALLOWED["fluxdrive_bringup"] = _ROS  # the package's __init__
for _job in ("record", "inspect", "replay"):
    ALLOWED[f"fluxdrive_bringup.{_job}"] = _ROS
ALLOWED["fluxdrive_bringup.view"] = _ROS | {_JOB["inspect"]}
ALLOWED["fluxdrive_bringup.launch"] = _ROS | {_JOB["inspect"], _JOB["record"]}
ALLOWED["fluxdrive_bringup.measure"] = ALLOWED["fluxdrive_bringup.launch"] | {_JOB["launch"]}
# the graph commands of ./fluxdrive: every job
ALLOWED["fluxdrive_bringup.cli"] = _ROS | {
    f"fluxdrive_bringup.{job}"
    for job in ("launch", "record", "inspect", "view", "measure", "replay")
}

# cycles still being taken apart this round, each named with the modules in it; the test fails
# when one of them is gone, so the list only shrinks
KNOWN_CYCLES: list[set[str]] = []

# command-line main()s outside cli/ still to move
KNOWN_MAINS: set[str] = set()


@cache
def modules() -> dict[str, Path]:
    """Every module of the engine and of the ROS packages, by dotted name."""
    roots = [REPO / "python"] + sorted(p for p in (REPO / "src").iterdir() if p.is_dir())
    out: dict[str, Path] = {}
    for base in roots:
        for f in base.rglob("*.py"):
            rel = f.relative_to(base)
            if (
                rel.parts[0] in ("build", "install", "log", "test")
                or rel.name == "setup.py"
                or rel.name.endswith(".launch.py")  # ROS 2 launch files, not modules
            ):
                continue
            parts = list(rel.with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if parts:
                out[".".join(parts)] = f
    return out


def imports_of(name: str, path: Path, known: dict[str, Path]) -> list[tuple[str, int]]:
    """(module imported, line) for every import in the file, resolved to the deepest known
    module (``from a.b import c`` names a.b.c when that is a module)."""
    tree = ast.parse(path.read_text(), str(path))
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.append((mod, node.lineno))
            found += [(f"{mod}.{a.name}", node.lineno) for a in node.names]
    out = []
    for mod, line in found:
        parts = mod.split(".")
        while parts and ".".join(parts) not in known:
            parts.pop()
        if parts:
            out.append((".".join(parts), line))
    return out


def package_of(module: str) -> str:
    parts = module.split(".")
    if parts[0] in ("fluxdrive", "fluxdrive_bringup"):  # a subpackage each (bringup: by job)
        return ".".join(parts[:2]) if len(parts) > 1 else "fluxdrive"
    return parts[0]


@cache
def graph() -> dict[str, dict[str, int]]:
    known = modules()
    g: dict[str, dict[str, int]] = {}
    for name, path in known.items():
        edges = g.setdefault(name, {})
        for target, line in imports_of(name, path, known):
            if target != name:
                edges.setdefault(target, line)
    return g


def cycles(g: dict[str, dict[str, int]]) -> list[set[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in g[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_every_package_is_in_the_table():
    assert {package_of(m) for m in modules()} <= set(ALLOWED)


def test_imports_follow_the_layers():
    g = graph()
    known = modules()
    bad = []
    for src, edges in sorted(g.items()):
        here = package_of(src)
        for dst, line in sorted(edges.items()):
            there = package_of(dst)
            if there != here and there not in ALLOWED[here]:
                bad.append(f"{known[src].relative_to(REPO)}:{line}: {src} imports {dst}")
    assert bad == [], "imports against the layers:\n" + "\n".join(bad)


def test_no_import_cycles():
    found = cycles(graph())
    new = [c for c in found if c not in KNOWN_CYCLES]
    assert new == [], f"import cycles: {[sorted(c) for c in new]}"
    gone = [c for c in KNOWN_CYCLES if c not in found]
    assert gone == [], f"no longer a cycle, remove it from KNOWN_CYCLES: {gone}"


def test_command_line_mains_live_in_cli():
    found = set()
    for name, path in modules().items():
        if not name.startswith("fluxdrive.") or package_of(name) == "fluxdrive.cli":
            continue
        tree = ast.parse(path.read_text(), str(path))
        if any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in tree.body):
            found.add(name)
    assert found - KNOWN_MAINS == set(), "a main() outside fluxdrive/cli"
    assert KNOWN_MAINS - found == set(), "moved: remove from KNOWN_MAINS"


def test_the_checker_sees_function_level_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from fluxdrive.drive import sim\n    return sim\n")
    known = {"fluxdrive.core.m": f, "fluxdrive.drive.sim": f, "fluxdrive.drive": f}
    assert imports_of("fluxdrive.core.m", f, known) == [
        ("fluxdrive.drive", 2),
        ("fluxdrive.drive.sim", 2),
    ]
    assert cycles({"a": {"b": 1}, "b": {"a": 1}, "c": {"a": 1}}) == [{"a", "b"}]
