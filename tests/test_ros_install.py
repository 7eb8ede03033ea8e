"""A ROS 2 install of the packages in src/: every package.xml dependency resolves on Jazzy
the way rosdep resolves it (against recorded entries of rosdistro's index), the launch files
describe the project's own graph files (read at launch time, one graph), and the colcon
build installs launch/ and config/ into share/.

What is not tested here: `ros2 launch` itself -- the launch and launch_ros Python packages
are not among the ROS wheels of this venv.  The launch files are parsed, imported and their
graph compared with the launcher's; the launch actions they make
(fluxdrive_bringup.launch.rosgraph._actions) never ran here."""

from __future__ import annotations

import ast
import importlib.util
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "src"
RECORDED = REPO / "tests" / "data" / "rosdistro"
INSTALL = REPO / ".ws" / "install"
LAUNCH_DIR = SRC / "fluxdrive_bringup" / "launch"
# Jazzy's Tier 1 platform (REP 2000), the one rosdep resolves for on a Jazzy install
OS_NAME, OS_CODENAME = "ubuntu", "noble"
DEPEND_TAGS = (
    "depend",
    "build_depend",
    "build_export_depend",
    "buildtool_depend",
    "buildtool_export_depend",
    "exec_depend",
    "test_depend",
    "doc_depend",
)
# launch file -> the graph file it must describe
LAUNCH_GRAPHS = {
    "demo.launch.py": "sim_lockstep.yaml",
    "tune.launch.py": "sim_paced.yaml",
    "bench.launch.py": "bench_real.yaml",
    "graph.launch.py": "sim_lockstep.yaml",
}


def _packages() -> dict[str, ET.Element]:
    return {p.parent.name: ET.parse(p).getroot() for p in sorted(SRC.glob("*/package.xml"))}


def _os_rule(rule: dict | None) -> object:
    """rosdep's rule for OS_NAME/OS_CODENAME from a key's entry (None: no rule)."""
    if not isinstance(rule, dict) or OS_NAME not in rule:
        return None
    r = rule[OS_NAME]
    if isinstance(r, dict) and not ({"pip", "apt", "packages"} & set(r)):
        r = r.get(OS_CODENAME, r.get("*"))  # per release, '*' for the others
    return r


def _resolve(key: str, workspace: set[str], ros: set[str], rules: dict) -> str | None:
    """How rosdep installs `key` on Jazzy/noble (None: it cannot)."""
    if key in workspace:
        return "this workspace"
    if key in ros:
        return "apt ros-jazzy-" + key.replace("_", "-")
    r = _os_rule(rules.get(key))
    if isinstance(r, list) and r:
        return "apt " + " ".join(r)
    if isinstance(r, dict):
        if "pip" in r and r["pip"] and r["pip"].get("packages"):
            return "pip " + " ".join(r["pip"]["packages"])
        if r.get("apt", {}).get("packages") or r.get("packages"):
            return "apt " + " ".join(r.get("apt", r).get("packages"))
    return None


def test_every_package_xml_dependency_resolves_on_jazzy():
    """`rosdep check --from-paths src --rosdistro jazzy`'s key resolution, offline: every
    dependency is a package of this workspace, a ROS package Jazzy releases
    (jazzy/distribution.yaml) or a rosdep key with a rule for Ubuntu noble (rosdep's
    python.yaml); the pip ones are pinned in requirements.lock like every Python
    dependency."""
    dist = yaml.safe_load((RECORDED / "jazzy-distribution.yaml").read_text())
    ros = {p for r in dist["repositories"].values() for p in r["release"]["packages"]}
    rules = yaml.safe_load((RECORDED / "python.yaml").read_text())
    assert OS_CODENAME in dist["release_platforms"][OS_NAME]
    pkgs = _packages()
    lock = {
        ln.split("==")[0].lower()
        for ln in (REPO / "requirements.lock").read_text().splitlines()
        if "==" in ln
    }
    unresolved, unpinned, table = [], [], {}
    for name, root in pkgs.items():
        for tag in DEPEND_TAGS:
            for el in root.findall(tag):
                key = (el.text or "").strip()
                how = _resolve(key, set(pkgs), ros, rules)
                table[key] = how
                if how is None:
                    unresolved.append(f"{name}: <{tag}>{key}")
                elif how.startswith("pip "):
                    unpinned += [f"{key} -> {d}" for d in how.split()[1:] if d.lower() not in lock]
    print(json.dumps(table, indent=1, sort_keys=True))
    assert not unresolved, f"no rosdep rule on Jazzy ({OS_CODENAME}): {unresolved}"
    assert not unpinned, f"pip packages of rosdep keys not in requirements.lock: {unpinned}"
    assert table["python3-rosbags-pip"] == "pip rosbags"
    assert table["rclpy"] == "apt ros-jazzy-rclpy"


def test_recorded_index_holds_only_what_the_packages_use():
    """The recorded entries stay small: each one is used by some package.xml."""
    keys = {
        (el.text or "").strip()
        for root in _packages().values()
        for tag in DEPEND_TAGS
        for el in root.findall(tag)
    }
    rules = yaml.safe_load((RECORDED / "python.yaml").read_text())
    assert set(rules) <= keys
    dist = yaml.safe_load((RECORDED / "jazzy-distribution.yaml").read_text())
    for repo, r in dist["repositories"].items():
        assert keys & set(r["release"]["packages"]), f"{repo} releases none of our dependencies"


def _launch_module(path: Path):
    ast.parse(path.read_text(), filename=str(path))  # a syntax error fails here, named
    spec = importlib.util.spec_from_file_location(path.name.replace(".", "_"), path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_launch_files_describe_the_project_graph_files():
    """Each launch file names a graph file of config/graphs and starts, per process of that
    graph, exactly the command the project's launcher starts (the container spec: classes,
    names, namespaces, parameter files, inline parameters), required where it is."""
    pytest.importorskip("rclpy")
    from fluxdrive_bringup.launch.launcher import Launcher, load_graph

    from fluxdrive_bringup.launch import rosgraph

    files = sorted(p.name for p in LAUNCH_DIR.glob("*.launch.py"))
    assert files == sorted(LAUNCH_GRAPHS)
    for name, graph in LAUNCH_GRAPHS.items():
        mod = _launch_module(LAUNCH_DIR / name)
        assert mod.GRAPH == graph and callable(mod.generate_launch_description)
        ours = load_graph(REPO / "config" / "graphs" / graph)
        launched = rosgraph.processes(rosgraph.load(graph, REPO))
        launcher = Launcher(ours)
        procs = ours.processes()
        assert [p.name for p in launched] == list(procs), name
        for p in launched:
            members = procs[p.name]
            argv = launcher._argv(p.name, members)
            if p.cmd is not None:
                assert p.cmd == argv
            else:
                assert argv[1:3] == ["-m", "fluxdrive_ros.runner"] and p.arguments == argv[3:]
                spec = json.loads(p.arguments[1])
                assert [n["name"] for n in spec["nodes"]] == [m.name for m in members]
            assert p.required == any(m.required for m in members)
    # a namespace given at launch moves the whole drive, as `launch --namespace` does
    g = rosgraph.configure("sim_paced", namespace="/bench_a", domain_id="37")
    assert g.domain_id == 37 and rosgraph.environment(g)["ROS_DOMAIN_ID"] == "37"
    assert all(p.arguments[-1] == "__ns:=/bench_a" for p in rosgraph.processes(g))


def test_colcon_install_puts_launch_and_config_into_share():
    """After the colcon build (tools/bootstrap.sh): share/fluxdrive_bringup holds launch/
    (every launch file) and config/ (the graph files, parameter files, scenarios, machine
    cards, the DBC), the container executable is where launch_ros looks for it, and the
    graph read from share/ is the graph read from the checkout."""
    share = INSTALL / "share" / "fluxdrive_bringup"
    if not share.is_dir():
        pytest.skip("no colcon install (.ws/install): run ./fluxdrive once")
    pytest.importorskip("rclpy")
    from fluxdrive_bringup.launch import rosgraph

    assert sorted(p.name for p in (share / "launch").glob("*.launch.py")) == sorted(LAUNCH_GRAPHS)
    for sub in ("graphs", "ros", "scenarios", "machines", "can"):
        ours = sorted(p.name for p in (REPO / "config" / sub).iterdir() if p.is_file())
        assert sorted(p.name for p in (share / "config" / sub).iterdir()) == ours, sub
    assert (INSTALL / "lib" / "fluxdrive_bringup" / "container").is_file()
    for graph in sorted(set(LAUNCH_GRAPHS.values())):
        a = rosgraph.processes(rosgraph.load(graph, REPO))
        b = rosgraph.processes(rosgraph.load(graph, share))
        assert [p.name for p in a] == [p.name for p in b]
        for pa, pb in zip(a, b, strict=True):
            if pa.cmd is not None:
                assert pa.cmd == pb.cmd
                continue
            na, nb = (json.loads(p.arguments[1])["nodes"] for p in (pa, pb))
            for x, y in zip(na, nb, strict=True):
                assert {k: v for k, v in x.items() if k != "params_files"} == {
                    k: v for k, v in y.items() if k != "params_files"
                }
                files = [Path(f) for f in y["params_files"]]
                assert all(share in f.parents for f in files), files
                assert [f.read_text() for f in files] == [
                    Path(f).read_text() for f in x["params_files"]
                ]
