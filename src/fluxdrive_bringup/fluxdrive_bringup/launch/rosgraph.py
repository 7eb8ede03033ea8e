"""The project's graph files as ROS 2 launch descriptions: `ros2 launch fluxdrive_bringup
demo.launch.py` starts the graph `./fluxdrive launch config/graphs/sim_lockstep.yaml` starts.

One graph, not two: a launch file of this package (launch/*.launch.py, installed to
share/fluxdrive_bringup/launch) only names a graph file of config/graphs (installed to
share/fluxdrive_bringup/config/graphs) and calls :func:`generate`; at launch time the graph
file is read with the launcher's own parser (every key checked, a bad one is one line naming
the file and the key) and each of its processes is started as the launcher starts it: the
`container` executable of this package with the process's container spec
(fluxdrive_ros.runner; :func:`fluxdrive_bringup.launch.launcher.container_spec`), or a `cmd`
entry as is.  Launch arguments: ``graph:=NAME`` (a file under config/graphs, or a path),
``namespace:=/bench_a``, ``domain_id:=N``.

What `ros2 launch` does not do that `./fluxdrive launch` does (the launcher is the tested
path; docs/graph.md): stop the recorder last and hand it the nodes' published counts, check
the bag against them, watch a plant's frames for a stall, refuse a domain other nodes use,
restart a process per `on_death: restart`.  `required: true` ends the launch when that
process ends, as in the launcher.
"""

from __future__ import annotations

import json
import os
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive_ros.topics import check_namespace

from fluxdrive_bringup.launch.launcher import Graph, container_spec, parse_graph

PACKAGE = "fluxdrive_bringup"
CONTAINER = "container"  # the package's executable that runs a container spec


@dataclass
class LaunchProcess:
    """One process of a graph as a launch action starts it: the package's `container` with
    `arguments`, or (a `cmd` entry) `cmd` as is."""

    name: str
    arguments: list[str] = field(default_factory=list)
    cmd: list[str] | None = None
    required: bool = False


def share_root() -> Path:
    """Where config/ lives: this package's share directory in a ROS 2 install (colcon),
    else the checkout."""
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory(PACKAGE))
    except (ImportError, LookupError, ValueError):
        return REPO_ROOT
    return share if (share / "config" / "graphs").is_dir() else REPO_ROOT


def load(graph: str | Path, root: Path | None = None) -> Graph:
    """The graph file `graph` (a path, or a name under <root>/config/graphs), its parameter
    files resolved against `root` (default :func:`share_root`)."""
    root = share_root() if root is None else Path(root)
    path = Path(graph)
    if not path.is_absolute() and not path.exists():
        name = path.name if path.suffix else path.name + ".yaml"
        path = root / "config" / "graphs" / name
    if not path.exists():
        raise ConfigError(f"graph '{graph}' not found (looked at {path})")
    try:
        raw = yamlio.load_file(path)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read graph: {yamlio.describe(exc)}") from exc
    return parse_graph(raw, str(path), root)


def processes(g: Graph) -> list[LaunchProcess]:
    """The graph's processes, in the launcher's order, as launch actions start them."""
    out = []
    for pname, members in g.processes().items():
        required = any(m.required for m in members)
        if members[0].cmd:
            out.append(LaunchProcess(pname, cmd=list(members[0].cmd), required=required))
            continue
        args = ["--spec-json", json.dumps(container_spec(pname, members))]
        if g.namespace:  # the whole drive under it (fluxdrive_ros.runner)
            args += ["--ros-args", "-r", f"__ns:={g.namespace}"]
        out.append(LaunchProcess(pname, arguments=args, required=required))
    return out


def environment(g: Graph) -> dict[str, str]:
    """What every process of the graph gets on top of the environment, as from the
    launcher: the discovery range, the domain, a graph key drawn per launch, the graph's env."""
    env = {
        "ROS_AUTOMATIC_DISCOVERY_RANGE": g.discovery_range,
        "FLUXDRIVE_GRAPH_KEY": os.environ.get("FLUXDRIVE_GRAPH_KEY") or secrets.token_hex(16),
        "PYTHONUNBUFFERED": "1",
    }
    if g.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(g.domain_id)
    env.update(g.env)
    return env


def configure(graph: str, namespace: str = "", domain_id: str = "") -> Graph:
    """The graph a launch starts: the file, with the launch arguments applied."""
    g = load(graph)
    if namespace:
        g.namespace = check_namespace(namespace, "namespace")
    if domain_id:
        try:
            g.domain_id = int(domain_id)
        except ValueError:
            raise ConfigError(f"domain_id must be an integer, got {domain_id!r}") from None
    return g


def _launch(module: str) -> Any:
    """A module of ROS 2 launch (launch, launch_ros): there only in a ROS 2 install."""
    import importlib

    return importlib.import_module(module)


def _actions(context: Any) -> list[Any]:
    """OpaqueFunction body: the graph file read now, at launch time."""
    actions_mod, ros_actions = _launch("launch.actions"), _launch("launch_ros.actions")
    ExecuteProcess, Shutdown, Node = (  # noqa: N806 - the launch API's class names
        actions_mod.ExecuteProcess,
        actions_mod.Shutdown,
        ros_actions.Node,
    )
    cfg = context.launch_configurations
    g = configure(cfg.get("graph", ""), cfg.get("namespace", ""), cfg.get("domain_id", ""))
    env = environment(g)
    root = str(share_root())
    actions: list[Any] = []
    for p in processes(g):
        kw: dict[str, Any] = {"output": "screen", "additional_env": env, "cwd": root}
        if p.required:
            kw["on_exit"] = [Shutdown(reason=f"required process {p.name} ended")]
        if p.cmd is not None:
            actions.append(ExecuteProcess(cmd=p.cmd, name=p.name, **kw))
        else:
            actions.append(Node(package=PACKAGE, executable=CONTAINER, arguments=p.arguments, **kw))
    return actions


def generate(graph: str) -> Any:
    """The LaunchDescription of a launch file whose default graph is `graph`."""
    launch, actions_mod = _launch("launch"), _launch("launch.actions")
    arg = actions_mod.DeclareLaunchArgument
    return launch.LaunchDescription(
        [
            arg("graph", default_value=graph, description="graph file"),
            arg("namespace", default_value="", description="drive namespace"),
            arg("domain_id", default_value="", description="ROS_DOMAIN_ID"),
            actions_mod.OpaqueFunction(function=_actions),
        ]
    )
