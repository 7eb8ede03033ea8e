"""Start a whole fluxdrive graph from a YAML description (there is no ros2 launch here).

Graph file (config/graphs/*.yaml)::

    name: sim_lockstep
    discovery_range: LOCALHOST        # default; SUBNET/SYSTEM_DEFAULT to open up
    domain_id: 42                     # optional; else the environment's ROS_DOMAIN_ID
    env: {FLUXDRIVE_EXECUTOR: events} # optional extra environment for every process
    nodes:
      - name: plant                   # node name (unique within its namespace)
        node: plant                   # plant | observer | controller | recorder | module:Class
        namespace: /                  # optional
        process: drive                # optional: nodes naming the same process share one
                                      #   (one DDS participant, in-process delivery); default:
                                      #   a process of its own, named after the node
        params: [config/ros/plant.yaml]     # ros__parameters files (relative to the repo)
        parameters: {scenario: config/scenarios/paper_2pct_150load.yaml}  # inline, win
        required: true                # its exit (code 0) ends the graph (the others get
                                      #   stop_grace_s, default 20 s, to end by themselves)
        on_death: stop                # when its process dies (signal, non-zero exit):
                                      #   stop (default) | restart | ignore
        max_restarts: 3               # restart: at most this many times, then stop
        restart_backoff_s: 1.0        # restart: wait 1, 2, 4, ... s before restart 1, 2, 3
      - name: bridge                  # any other program, started as is
        cmd: [python, -m, some.module]
    on_death: stop                    # graph-wide defaults of the three keys above

Every process gets the parent's whole environment (the ROS wheels need it) plus
ROS_AUTOMATIC_DISCOVERY_RANGE from the graph's `discovery_range` (default LOCALHOST, whatever
the environment says: leaving the machine is an explicit opt-in in the graph file) and
FLUXDRIVE_GRAPH_KEY, a random key per launch that marks the graph's commands
(fluxdrive_ros.access).
Output lines are prefixed with the process name.  Ctrl-C (or SIGTERM) is forwarded as
SIGINT to every process (each finalises: the recorder closes its bag), then SIGTERM and
SIGKILL after timeouts; processes holding a recorder are stopped last, once the others have
ended (each waits until the recorder has acknowledged what it published), and are handed the
nodes' published counts first, so that the bag gets every message they published.  Before
anything starts, every recorder's bag directory is checked (new, writable, `min_free_mb` free).

A process that dies (killed by a signal, or a non-zero exit code) is reported with its
nodes, pid and signal/code and handled per its nodes' `on_death`: stop the graph (exit code
1), restart it (FLUXDRIVE_RESTART_COUNT=n in its environment; its sample readers then start
from the live samples, not the writers' history) up to `max_restarts` times with a doubling
back-off, or ignore it (the graph runs on; exit code unaffected).  A process that ends with
0 just leaves the graph (a `required` one takes the rest down with it).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from fluxdrive.core import schema, yamlio
from fluxdrive.core.machine import ConfigError
from fluxdrive.core.paths import check_output
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive.io.graphfile import (
    NODE_KEYS,
    TOP_KEYS,
    DeathPolicy,
    GraphSettings,
    ServeOptions,
    check_keys,
)
from fluxdrive_ros.runner import (
    NODE_CLASSES,
    PROCESS_ENV,
    REPORTING_ENV,
    STOP_COUNTS_ENV,
    STOP_DIR_ENV,
)
from fluxdrive_ros.topics import check_namespace

_POLICY_KEYS = set(schema.specs(DeathPolicy))


# the graph processes' Fast DDS profile (config/dds/fastdds_profiles.xml says why), and the
# variables by which Fast DDS 2 and 3 take one
DDS_PROFILES = REPO_ROOT / "config" / "dds" / "fastdds_profiles.xml"
DDS_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


@dataclass
class NodeSpec:
    name: str
    node: str | None = None
    namespace: str = ""
    process: str = ""
    params: list[str] = field(default_factory=list)
    parameters: dict[str, Any] = field(default_factory=dict)
    required: bool = False
    cmd: list[str] | None = None
    on_death: str | None = None  # None: the graph's default
    max_restarts: int | None = None
    restart_backoff_s: float | None = None

    @property
    def is_recorder(self) -> bool:
        if not self.node:
            return False
        return NODE_CLASSES.get(self.node, self.node) == NODE_CLASSES["recorder"]

    @property
    def fqn(self) -> str:
        ns = self.namespace.strip("/")
        return f"/{ns}/{self.name}" if ns else f"/{self.name}"


@dataclass
class Graph:
    name: str
    nodes: list[NodeSpec]
    discovery_range: str = GraphSettings.discovery_range
    domain_id: int | None = None
    env: dict[str, str] = field(default_factory=dict)
    stop_timeout_s: float = GraphSettings.stop_timeout_s
    stop_grace_s: float = GraphSettings.stop_grace_s
    # a graph with a plant: the first frame must come within start_timeout_s of the start,
    # and then at least one frame per second of wall time over any stall_timeout_s (a
    # lockstep plant whose controller is silent steps one PWM-off period per
    # duty_timeout_s: far below); otherwise the graph is stopped with one line
    start_timeout_s: float = GraphSettings.start_timeout_s
    stall_timeout_s: float = GraphSettings.stall_timeout_s
    source: str = ""
    on_death: str = DeathPolicy.on_death
    max_restarts: int = DeathPolicy.max_restarts
    restart_backoff_s: float = DeathPolicy.restart_backoff_s
    namespace: str = ""  # the drive's namespace: every node under it (`__ns:=`), e.g. /a
    # sharing its ROS domain with other graphs (--shared-domain): /clock, which carries no
    # graph id, is remapped to the graph's own (fluxdrive_ros.graph.private_topic)
    shared_domain: bool = False

    def policy(self, members: list[NodeSpec]) -> tuple[str, int, float]:
        """(on_death, max_restarts, restart_backoff_s) of a process (its nodes agree)."""
        m = members[0]
        return (
            m.on_death or self.on_death,
            self.max_restarts if m.max_restarts is None else m.max_restarts,
            self.restart_backoff_s if m.restart_backoff_s is None else m.restart_backoff_s,
        )

    def processes(self) -> dict[str, list[NodeSpec]]:
        out: dict[str, list[NodeSpec]] = {}
        for n in self.nodes:
            out.setdefault(n.process or n.name, []).append(n)
        return out

    def to_dict(self) -> dict:
        nodes = []
        for n in self.nodes:
            d: dict[str, Any] = {"name": n.name}
            if n.cmd:
                d["cmd"] = list(n.cmd)
            else:
                d["node"] = n.node
            for k in ("namespace", "process"):
                if getattr(n, k):
                    d[k] = getattr(n, k)
            if n.params:
                d["params"] = list(n.params)
            if n.parameters:
                d["parameters"] = dict(n.parameters)
            if n.required:
                d["required"] = True
            for k in sorted(_POLICY_KEYS):
                if getattr(n, k) is not None:
                    d[k] = getattr(n, k)
            nodes.append(d)
        out: dict[str, Any] = {"name": self.name, "discovery_range": self.discovery_range}
        if self.namespace:
            out["namespace"] = self.namespace
        if self.domain_id is not None:
            out["domain_id"] = self.domain_id
        if self.env:
            out["env"] = dict(self.env)
        policy = (self.on_death, self.max_restarts, self.restart_backoff_s)
        if policy != (
            DeathPolicy.on_death,
            DeathPolicy.max_restarts,
            DeathPolicy.restart_backoff_s,
        ):
            out.update(
                on_death=self.on_death,
                max_restarts=self.max_restarts,
                restart_backoff_s=self.restart_backoff_s,
            )
        out["nodes"] = nodes
        return out


def _resolve(p: str | Path, base: Path) -> Path:
    p = Path(p)
    if p.is_absolute():
        return p
    for root in (base, REPO_ROOT):
        if (root / p).exists():
            return root / p
    return REPO_ROOT / p


def _policy(d: dict) -> dict[str, Any]:
    """The on_death keys a node entry or the graph gives (checked by check_keys)."""
    out = {k: d[k] for k in _POLICY_KEYS if d.get(k) is not None}
    if "restart_backoff_s" in out:
        out["restart_backoff_s"] = float(out["restart_backoff_s"])
    return out


_ENV_VALUE_MAX = 32_768


def parse_graph(raw: Any, src: str = "graph", base: Path = REPO_ROOT) -> Graph:
    """A graph file's mapping as a Graph; every key checked by its field
    (fluxdrive.io.graphfile), a bad one: ConfigError naming `src` and the key."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: a graph must be a mapping with a 'nodes' list")
    check_keys(raw, TOP_KEYS, src)
    nodes_raw = raw.get("nodes")
    if not nodes_raw:
        raise ConfigError(f"{src}: nodes must be a non-empty list")
    nodes = []
    seen = set()
    for where, nd in _expand_observers(nodes_raw, src, base):
        spec = _parse_node(nd, where, base)
        if spec.fqn in seen:
            raise ConfigError(f"{where}: node {spec.fqn} appears twice")
        seen.add(spec.fqn)
        nodes.append(spec)
    given = {k: v for k, v in raw.items() if v is not None and k in schema.specs(GraphSettings)}
    g = Graph(
        name=str(given.get("name", Path(src).stem)),
        namespace=check_namespace(raw.get("namespace"), f"{src}: namespace"),
        nodes=nodes,
        discovery_range=str(given.get("discovery_range", Graph.discovery_range)).upper(),
        domain_id=given.get("domain_id"),
        env=_parse_env(given.get("env", {}), src),
        source=src,
        **_policy(raw),
    )
    for k in _TIMEOUT_KEYS:  # given: checked by their fields
        if k in given:
            setattr(g, k, float(given[k]))
    _check_processes(g, src)
    return g


_TIMEOUT_KEYS = ("stop_timeout_s", "stop_grace_s", "start_timeout_s", "stall_timeout_s")


def _expand_observers(nodes_raw: Any, src: str, base: Path) -> list[tuple[str, Any]]:
    """(where, entry) of the graph's `nodes`, an `observers_of: SCENARIO` entry
    standing for one entry per observer of that scenario (the set declared once, in the
    scenario's observers), named after it."""
    if not isinstance(nodes_raw, list):
        raise ConfigError(f"{src}: nodes must be a non-empty list")
    out: list[tuple[str, Any]] = []
    for i, nd in enumerate(nodes_raw):
        where = f"{src}: nodes[{i}]"
        if not isinstance(nd, dict) or "observers_of" not in nd:
            out.append((where, nd))
            continue
        sp = nd["observers_of"]
        if not isinstance(sp, str) or not sp or "\0" in sp or "name" in nd:
            raise ConfigError(
                f"{where}: observers_of must be a scenario file's path, and the entry has no name"
            )
        from fluxdrive.drive.scenario import observer_names

        rest = {k: v for k, v in nd.items() if k != "observers_of"}
        for name in observer_names(_resolve(sp, base)):
            out.append((f"{where} ({name}, observers_of)", {**rest, "name": name}))
    return out


def _parse_node(nd: Any, where: str, base: Path) -> NodeSpec:
    """One entry of the graph's `nodes` (where: its place in the file)."""
    if not isinstance(nd, dict):
        raise ConfigError(f"{where} must be a mapping")
    if isinstance(nd.get("params"), str):  # one file
        nd = {**nd, "params": [nd["params"]]}
    name = nd.get("name")
    here = f"{where} ({name})" if isinstance(name, str) and name else where
    check_keys(nd, NODE_KEYS, here)
    if not isinstance(name, str) or not name.replace("_", "a").isalnum():
        raise ConfigError(f"{where}: name must be a ROS name (letters, digits, _), got {name!r}")
    node, cmd = _node_or_cmd(nd, here)
    files = _param_files(nd.get("params") or [], here, base)
    parameters = nd.get("parameters") or {}
    if not all(isinstance(k, str) for k in parameters):
        raise ConfigError(f"{here}: parameters must be a mapping name -> value")
    ns = str(nd.get("namespace", "") or "")
    if ns and not ns.startswith("/"):
        ns = "/" + ns
    spec = NodeSpec(
        name=name,
        node=node,
        namespace=ns.rstrip("/"),
        process=str(nd.get("process", "") or ""),
        params=files,
        parameters=dict(parameters),
        required=bool(nd.get("required") or False),
        cmd=cmd,
        **_policy(nd),
    )
    if spec.is_recorder and spec.on_death == "restart":
        raise ConfigError(
            f"{here}: 'on_death: restart' is not supported for a "
            f"recorder (its bag directory exists after the first start); "
            f"use stop or ignore"
        )
    return spec


def _node_or_cmd(nd: dict, here: str) -> tuple[str | None, list[str] | None]:
    """A node's class (a known node or module:Class) or its command, exactly one of them
    (their types checked by check_keys)."""
    node, cmd = nd.get("node"), nd.get("cmd")
    if (node is None) == (cmd is None):
        raise ConfigError(
            f"{here}: give exactly one of 'node' (one of "
            f"{sorted(NODE_CLASSES)} or module:Class) and 'cmd'"
        )
    if node is not None and node not in NODE_CLASSES and ":" not in node:
        raise ConfigError(
            f"{here}: node must be one of {sorted(NODE_CLASSES)} or module:Class, got {node!r}"
        )
    if cmd is not None and not cmd:
        raise ConfigError(f"{here}: cmd must be a non-empty list of strings")
    if node is not None and node not in NODE_CLASSES:
        _check_node_class(node, here)
    return node, None if cmd is None else list(cmd)


def _check_node_class(node: str, here: str) -> None:
    """A user's node class `module:Class`: its module must be found on the Python path
    before anything starts (without running it: a process would fail at start with a
    traceback and the graph with 'exit 1')."""
    import importlib.util

    mod, _, cls = node.partition(":")
    why = ""
    if not cls.isidentifier() or not all(p.isidentifier() for p in mod.split(".")):
        why = "expected module.path:ClassName"
    else:
        try:
            if importlib.util.find_spec(mod) is None:
                why = f"no module named {mod!r} on the Python path"
        except Exception as exc:  # noqa: BLE001 - a parent package that fails to import
            why = f"cannot look up module {mod!r}: {type(exc).__name__}: {exc}".splitlines()[0]
    if why:
        raise ConfigError(f"{here}: node class {node!r}: {why}")


def _param_files(params: Any, here: str, base: Path) -> list[str]:
    """A node's parameter files (a list of strings: check_keys): each found and valid YAML."""
    files = []
    for p in params:
        if not p or "\0" in p:
            raise ConfigError(f"{here}: params entries must be file paths, got {p!r}")
        f = _resolve(p, base)
        if not f.exists():
            raise ConfigError(f"{here}: parameter file {p} not found")
        try:
            yamlio.load_file(f)
        except (OSError, yamlio.YAMLError) as exc:
            raise ConfigError(f"{f}: not valid YAML: {yamlio.describe(exc)}") from exc
        files.append(str(f))
    return files


def _parse_env(env: Any, src: str) -> dict[str, str]:
    """The graph's `env` (a mapping: check_keys): variable names and scalar values."""
    for k, v in env.items():
        # an environment variable is a name and a scalar; Linux takes at most 128 kB each
        if not isinstance(k, str) or not k or "=" in k or "\0" in k:
            raise ConfigError(f"{src}: 'env': {k!r} is not an environment variable name")
        if isinstance(v, (dict, list)) or v is None:
            raise ConfigError(
                f"{src}: 'env.{k}' must be a string or number, got {type(v).__name__}"
            )
        if len(str(v)) > _ENV_VALUE_MAX or "\0" in str(v):
            raise ConfigError(
                f"{src}: 'env.{k}' is {len(str(v))} characters (at most {_ENV_VALUE_MAX}, no NUL)"
            )
    return {str(k): str(v) for k, v in env.items()}


def _check_processes(g: Graph, src: str) -> None:
    """The nodes of one process: no 'cmd' among others, one death policy, no restarted
    recorder."""
    for pname, members in g.processes().items():
        if len(members) > 1 and any(m.cmd for m in members):
            raise ConfigError(f"{src}: process '{pname}' mixes a 'cmd' with other nodes")
        pols = {m.name: g.policy([m]) for m in members}
        if len(set(pols.values())) > 1:
            raise ConfigError(
                f"{src}: the nodes of process '{pname}' disagree on on_death/"
                f"max_restarts/restart_backoff_s ({pols}); give them one policy"
            )
        if any(m.is_recorder for m in members) and pols[members[0].name][0] == "restart":
            raise ConfigError(
                f"{src}: process '{pname}' holds a recorder: 'on_death: "
                f"restart' is not supported for it (its bag directory exists "
                f"after the first start); use stop or ignore"
            )


def load_graph(path: str | Path) -> Graph:
    path = Path(path)
    if not path.exists():
        cand = REPO_ROOT / "config" / "graphs" / (path.name if path.suffix else path.name + ".yaml")
        if cand.exists():
            path = cand
        else:
            raise ConfigError(f"graph '{path}' not found (looked at {path} and {cand})")
    try:
        raw = yamlio.load_file(path)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read graph: {yamlio.describe(exc)}") from exc
    return parse_graph(raw, str(path), path.parent)


# ---------------------------------------------------------------------------- running
# the start phase (stall watch: start_timeout_s) lasts until this frame: the controller and
# observers answer from the first frames on, once their kernels are compiled
START_FRAMES = 50


def _libc_prctl():
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux
        return None


_PRCTL = _libc_prctl()
_PR_SET_PDEATHSIG = 1


def _die_with_launcher() -> None:
    """In a graph process before exec: SIGTERM when the launcher goes away (killed,
    crashed), so that no process of a graph outlives it (they run in sessions of their own
    and would otherwise go on, e.g. answering a later graph on the same domain)."""
    if _PRCTL is not None:
        _PRCTL(_PR_SET_PDEATHSIG, int(signal.SIGTERM))


def node_parameters(n: NodeSpec) -> dict[str, Any]:
    """A node's parameter values as the graph gives them: its parameter files' sections
    for /** and for the node (ros__parameters), then the inline `parameters`."""
    out: dict[str, Any] = {}
    for f in n.params:
        try:
            data = yamlio.load_file(f) or {}
        except (OSError, yamlio.YAMLError):
            continue
        if not isinstance(data, dict):
            continue
        for key in ("/**", "**", n.fqn.lstrip("/"), n.fqn):
            sec = data.get(key)
            if isinstance(sec, dict) and isinstance(sec.get("ros__parameters"), dict):
                out.update(sec["ros__parameters"])
    out.update(n.parameters)
    return out


def container_spec(pname: str, members: list[NodeSpec]) -> dict[str, Any]:
    """The container spec (fluxdrive_ros.runner) of the graph process `pname` holding the
    node entries `members`: what the launcher starts, and what the ROS 2 launch files start
    (fluxdrive_bringup.launch.rosgraph)."""
    return {
        "process": pname,
        "nodes": [
            {
                "class": m.node,
                "name": m.name,
                "namespace": m.namespace,
                "parameters": m.parameters,
                "params_files": m.params,
            }
            for m in members
        ],
    }


# a process's last lines kept for its death line (Proc.fatal_line)
TAIL_LINES = 40
_FATAL = re.compile(
    r"\[(ERROR|FATAL)\]|\b(ERROR|FATAL)\b|cannot start|^\w+(\.\w+)*(Error|Exception): "
)


class Proc:
    def __init__(
        self,
        name: str,
        nodes: list[NodeSpec],
        argv: list[str],
        policy: tuple[str, int, float] = ("stop", 3, 1.0),
    ):
        self.name = name
        self.nodes = nodes
        self.argv = argv
        self.popen: subprocess.Popen | None = None
        self.code: int | None = None
        self.reader: threading.Thread | None = None
        self.on_death, self.max_restarts, self.backoff_s = policy
        self.restarts = 0
        self.restart_at: float | None = None
        self.done = False  # ended for good (normally, stopped, or died and ignored)
        self.ignored = False
        self.bag_open: str | None = None  # bag directory its recorder opened
        self.t_last_line = time.monotonic()  # when it last wrote a line (progress included)
        self.tail: deque[str] = deque(maxlen=TAIL_LINES)  # its last output lines

    def fatal_line(self) -> str:
        """The line that says why it ended: its last error line (a logged ERROR/FATAL, a
        `cannot start`, a traceback's exception line), else its last line; "" if silent."""
        lines = [ln for ln in self.tail if ln.strip()]
        for ln in reversed(lines):
            if _FATAL.search(ln):
                return ln.strip()
        return lines[-1].strip() if lines else ""

    @property
    def process(self) -> subprocess.Popen:
        """The running (or ended) process; only asked for once it has been spawned."""
        if self.popen is None:
            raise RuntimeError(f"process {self.name} was never started")
        return self.popen

    @property
    def has_recorder(self) -> bool:
        return any(n.is_recorder for n in self.nodes)

    @property
    def label(self) -> str:
        names = ", ".join(n.fqn for n in self.nodes)
        return f"'{self.name}'" + (f" ({names})" if names != f"/{self.name}" else "")


class Launcher:
    """Runs a Graph: start, stream prefixed output, watch, stop."""

    def __init__(
        self,
        graph: Graph,
        out=None,
        quiet: bool = False,
        progress: bool = True,
        log_dir: Path | None = None,
    ):
        self.g = graph
        self.out = out or sys.stdout
        self.quiet = quiet
        self.show_progress = progress
        self.log_dir = log_dir
        self.procs: list[Proc] = []
        self.bags: list[str] = []
        self.scope_urls: list[str] = []
        self.progress: tuple[int, int, float] | None = None
        self.progress_ts_s = 1e-4  # until the plant says its own period (@progress)
        self.lock = threading.Lock()
        self.stopping = False
        self.interrupted = False
        self.stop_signal = 0  # the signal that stopped the graph (run())
        self.failed: list[Proc] = []
        self.timed_out = False  # run(timeout) reached its timeout (and stopped the graph)
        self.ignored: list[Proc] = []
        self.restarts: dict[str, int] = {}  # process name -> restarts so far
        self._spawn_lock = threading.Lock()  # no restart once a stop has begun
        self._progress_shown = False
        self._last_progress_print = 0.0
        self._t_start: float | None = None  # monotonic time of start()
        self._watch_frames = False  # a plant that reports progress: stalls are watched
        self._frames: deque[tuple[float, int]] = deque()  # (monotonic, frame) of progress
        self.last_warning = ""  # the newest warning/error line of any process
        self.published: dict[str, int] = {}  # topic -> messages its nodes published
        self._stop_dir: Path | None = None  # the recorders' counts files (stop())
        self.tty = hasattr(sys.stderr, "isatty") and sys.stderr.isatty()

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        # discovery: the graph decides (default LOCALHOST); leaving this machine is an opt-in
        # in the graph file (discovery_range: SUBNET | SYSTEM_DEFAULT), never inherited
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = self.g.discovery_range
        # one random key per launch (kept across restarts): commands are obeyed only with
        # a mark made with it (fluxdrive_ros.access); an explicit one in the environment wins
        if not getattr(self, "_graph_key", None):
            import secrets

            self._graph_key = os.environ.get("FLUXDRIVE_GRAPH_KEY") or secrets.token_hex(16)
        env["FLUXDRIVE_GRAPH_KEY"] = self._graph_key
        if self.g.domain_id is not None:
            env["ROS_DOMAIN_ID"] = str(self.g.domain_id)
        env.update(self.g.env)
        # the graph's Fast DDS profile (writers' heartbeat 0.1 s: a stop waits for its
        # readers' last acknowledgement that long, not up to 3 s); a profile named in the
        # environment or the graph's env wins
        if not any(k in env for k in DDS_PROFILE_VARS):
            env[DDS_PROFILE_VARS[0]] = str(DDS_PROFILES)
        env["PYTHONUNBUFFERED"] = "1"
        env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
        env.setdefault("RCUTILS_CONSOLE_OUTPUT_FORMAT", "[{severity}] [{name}]: {message}")
        return env

    def _argv(self, pname: str, members: list[NodeSpec]) -> list[str]:
        if members[0].cmd:
            return list(members[0].cmd)
        spec = container_spec(pname, members)
        argv = [sys.executable, "-m", "fluxdrive_ros.runner", "--spec-json", json.dumps(spec)]
        if self.g.namespace:  # the whole drive under it (fluxdrive_ros.runner)
            argv += ["--ros-args", "-r", f"__ns:={self.g.namespace}"]
        elif self.private_topics:
            argv += ["--ros-args"]
            for shared, own in self.private_topics.items():
                argv += ["-r", f"{shared}:={own}"]
        return argv

    @property
    def private_topics(self) -> dict[str, str]:
        """Shared topic -> this graph's own name for it, for a graph sharing its domain in
        the root namespace (/clock, /diagnostics, /rosout: their messages carry no graph id,
        so two such graphs would read and record each other's); empty otherwise."""
        if self.g.namespace or not self.g.shared_domain:
            return {}
        from fluxdrive_ros.graph import SHARED_TOPICS, id_from_key, private_topic

        self.env()  # the graph key (drawn once per launch)
        gid = id_from_key(self._graph_key)
        return {t: private_topic(gid, t) for t in SHARED_TOPICS}

    def bag_name(self, topic: str) -> str:
        """The name a topic the nodes publish has in the bag: the recorder names the
        drive's topics as a drive in the root namespace would, and the graph's own clock,
        diagnostics and log topics by their shared names."""
        for shared, own in self.private_topics.items():
            if topic == own:
                return shared
        ns = self.g.namespace
        if ns and topic.startswith(ns + "/"):
            return topic[len(ns) :]
        return topic

    @property
    def clock_topic(self) -> str:
        """The topic this graph's sim time goes on: /clock (the ROS convention: `topic echo
        /clock`, Foxglove) -- or, in a namespace, <ns>/clock (fluxdrive_ros.runner) -- unless
        the graph shares its domain in the root namespace: then its own
        /fluxdrive/graph_<id>/clock, so that no graph reads or records another's clock."""
        if self.g.namespace:
            return self.g.namespace + "/clock"
        return self.private_topics.get("/clock", "/clock")

    def preflight(self) -> None:
        """Before anything starts: every recorder's bag directory must be new and writable,
        with the recorder's min_free_mb free (ConfigError naming the node otherwise)."""
        from fluxdrive.io.bagwriter import check_bag_target

        for n in self.g.nodes:
            if not n.is_recorder:
                continue
            pv = node_parameters(n)
            bag = pv.get("bag_dir") or ""
            target = Path(str(bag)) if bag else REPO_ROOT / "bags" / "run-new"
            if not target.is_absolute():
                target = REPO_ROOT / target
            try:
                min_free = float(pv.get("min_free_mb", 100.0))
                check_bag_target(target, min_free, must_not_exist=bool(bag))
            except (TypeError, ValueError) as exc:
                raise ConfigError(
                    f"{self.g.source or self.g.name}: recorder {n.fqn}: {exc}"
                ) from exc

    def start(self) -> None:
        self._t_start = time.monotonic()
        plants = [n for n in self.g.nodes if n.node == "plant"]
        self._watch_frames = bool(plants) and all(
            float(node_parameters(n).get("progress_interval_s", 0.5) or 0) > 0 for n in plants
        )
        self.preflight()
        from fluxdrive_bringup.launch.kernels import KERNEL_NODES, warm_for_graph

        # no node compiles on its first frame (a silent stall otherwise); the start phase
        # (start_timeout_s) begins with the processes
        warm_for_graph(
            (node_parameters(n).get("scenario") for n in self.g.nodes if n.node in KERNEL_NODES),
            lambda text: self._emit(f"[launch] {text}"),
        )
        self._t_start = time.monotonic()
        env = self.env()
        # a recorder whose launcher is killed reads there what the others published
        env[STOP_DIR_ENV] = str(self._stop_directory())
        env[REPORTING_ENV] = ",".join(
            pname for pname, members in self.g.processes().items() if not members[0].cmd
        )
        if self._restart_transport(dict(env)) and not self.quiet:
            self._emit(
                "[launch] on_death: restart in the graph: Fast DDS without shared "
                "memory (FASTDDS_BUILTIN_TRANSPORTS=UDPv4), which does not carry a "
                "restarted process's messages after a SIGKILL"
            )
        for pname, members in self.g.processes().items():
            p = Proc(pname, members, self._argv(pname, members), self.g.policy(members))
            self._spawn(p, env)
            self.procs.append(p)
            if not self.quiet:
                self._emit(f"[launch] process {p.label} started (pid {p.process.pid})")

    def _restart_transport(self, env: dict[str, str]) -> bool:
        """Graphs with on_death: restart run Fast DDS without its shared-memory transport
        (UDP on loopback instead): after a SIGKILL, Fast DDS 2.14's shared memory no longer
        carries a restarted process's messages to the readers that were already there
        (a known Fast DDS 2.14 defect).  An explicit FASTDDS_BUILTIN_TRANSPORTS wins."""
        if not any(self.g.policy([n])[0] == "restart" for n in self.g.nodes):
            return False
        if not env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
            return False
        if "FASTDDS_BUILTIN_TRANSPORTS" in env:
            return False
        env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
        return True

    def _spawn(self, p: Proc, env: dict[str, str] | None = None) -> None:
        env = dict(env or self.env())
        self._restart_transport(env)
        if p.restarts:
            env["FLUXDRIVE_RESTART_COUNT"] = str(p.restarts)
        env[PROCESS_ENV] = p.name
        if p.has_recorder:
            env[STOP_COUNTS_ENV] = str(self._counts_file(p))
        p.code = None
        p.popen = subprocess.Popen(
            p.argv,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            cwd=str(REPO_ROOT),
            preexec_fn=_die_with_launcher,
        )  # noqa: PLW1509
        p.reader = threading.Thread(target=self._pump, args=(p,), daemon=True)
        p.reader.start()

    def _emit(self, text: str) -> None:
        with self.lock:
            if self._progress_shown and self.tty:
                sys.stderr.write("\r\033[K")
                self._progress_shown = False
            self.out.write(text + "\n")
            self.out.flush()

    def _pump(self, p: Proc) -> None:
        logf = None
        if self.log_dir is not None:
            try:  # checked before the start (--log-dir); a disk can still fill or turn read-only
                self.log_dir.mkdir(parents=True, exist_ok=True)
                logf = open(self.log_dir / f"{p.name}.log", "a" if p.restarts else "w")  # noqa: SIM115
            except OSError as exc:  # the process's output is still read (a full pipe blocks it)
                self._emit(f"[launch] no log file for {p.name} in {self.log_dir}: {exc.strerror}")
        assert p.popen and p.popen.stdout
        for raw in p.popen.stdout:
            p.t_last_line = time.monotonic()
            line = raw.decode(errors="replace").rstrip("\n")
            if line.startswith("@progress "):
                self._on_progress(line)
                continue
            if line.startswith("@bag "):
                self.bags.append(line[5:].strip())
                continue
            if line.startswith("@bag-open "):
                p.bag_open = line[10:].strip()
                continue
            if line.startswith("@published "):  # a node's message count on one topic
                try:
                    topic, n_text = line.split()[1:3]
                    with self.lock:
                        self.published[topic] = self.published.get(topic, 0) + int(n_text)
                except ValueError:
                    pass
                continue
            if line.startswith("@scope-url "):  # the scope server's address (--scope)
                self.scope_urls.append(line[11:].strip())
                continue
            if "WARN" in line or "ERROR" in line:
                self.last_warning = f"[{p.name}] {line}"
            p.tail.append(line)
            if logf:
                try:
                    logf.write(line + "\n")
                    logf.flush()
                except OSError as exc:  # a full disk: say so once, keep reading the output
                    self._emit(f"[launch] log file of {p.name} stopped: {exc.strerror}")
                    with contextlib.suppress(OSError):
                        logf.close()
                    logf = None
            if not self.quiet:
                self._emit(f"[{p.name}] {line}")
        if logf:
            logf.close()

    def _on_progress(self, line: str) -> None:
        fields = line.split()[1:]
        try:
            k_text, n_text, wall_text = fields[:3]
            self.progress = (int(k_text), int(n_text), float(wall_text))
            # the plant's PWM period [s] (its card's), so a 20 kHz card reads right
            if len(fields) > 3 and 0.0 < float(fields[3]) < 1.0:
                self.progress_ts_s = float(fields[3])
        except ValueError:
            return
        now = time.monotonic()
        if self._frames and self.progress[0] < self._frames[-1][1]:
            self._frames.clear()  # a restarted plant counts from 0 again
        self._frames.append((now, self.progress[0]))
        while len(self._frames) > 2 and self._frames[1][0] < now - self.g.stall_timeout_s:
            self._frames.popleft()
        if not self.show_progress:
            return
        k, n, wall = self.progress
        ts = self.progress_ts_s
        sim = k * ts
        rtf = sim / wall if wall > 0 else 0.0
        total = f"/{n * ts:.2f}" if n < 2**62 else ""
        text = (
            f"[progress] {sim:7.2f}{total} s simulated, {wall:6.1f} s wall, "
            f"real-time factor {rtf:.3f}"
        )
        with self.lock:
            if self.tty:
                sys.stderr.write("\r\033[K" + text)
                sys.stderr.flush()
                self._progress_shown = True
            elif time.monotonic() - self._last_progress_print > 5.0 or k >= n:
                self._last_progress_print = time.monotonic()
                self.out.write(text + "\n")
                self.out.flush()

    def signal_all(self, sig: int, procs: list[Proc] | None = None) -> None:
        for p in procs if procs is not None else self.procs:
            if p.popen and p.popen.poll() is None:
                try:
                    os.killpg(p.popen.pid, sig)
                except ProcessLookupError:
                    pass

    def check_recorded(self) -> dict[str, tuple[int, int]]:
        """Each finalised bag against what the nodes published (their `@published` counts
        at exit): one line per topic the bag holds fewer messages of (and the shortfall
        in its metadata.yaml, custom_data `fluxdrive_missing`), or one line that it holds
        them all.  Returns {topic: (recorded, published)} of the shortfalls."""
        from fluxdrive.io.bagio import bag_counts, note_missing

        short: dict[str, tuple[int, int]] = {}
        for bag in self.bags:
            try:
                counts, _ = bag_counts(Path(bag))
            except Exception as exc:  # noqa: BLE001 - not finalised, damaged: say so
                self._emit(f"[launch] WARNING: bag {bag}: cannot count its messages ({exc})")
                continue
            checked = 0
            missing: dict[str, dict[str, int]] = {}
            for name, n_pub in sorted(self.published.items()):
                topic = self.bag_name(name)
                if topic not in counts or n_pub == 0:
                    continue  # not recorded by this bag
                checked += 1
                if counts[topic] < n_pub:
                    short[topic] = (counts[topic], n_pub)
                    missing[topic] = {"recorded": counts[topic], "published": n_pub}
                    self._emit(
                        f"[launch] WARNING: bag {bag} holds {counts[topic]} of the {n_pub} "
                        f"messages published on {topic} ({n_pub - counts[topic]} missing)"
                    )
            if missing:
                note_missing(
                    Path(bag), missing, "launcher: recorded vs published at the nodes' exit"
                )
            if checked and not missing:
                self._emit(
                    f"[launch] bag {bag}: holds every message the nodes published on the "
                    f"{checked} topics it records"
                )
        return short

    def stalled(self, now: float) -> str | None:
        """Why a graph with a plant is stuck (start or run phase), or None.  The drain
        after the plant's last frame is bounded by stop_grace_s, the stop by
        stop_timeout_s."""
        g = self.g
        if self.stopping or self._t_start is None:
            return None
        if not self._watch_frames:
            return None  # no frames to watch (a replay, a scope, progress lines off)
        plant_done = any(p.done for p in self.procs if any(n.node == "plant" for n in p.nodes))
        if self.progress is None or self.progress[0] < START_FRAMES:
            # starting: processes, discovery, the first answers (kernels compiling)
            if now - self._t_start > g.start_timeout_s:
                at = "no frame" if self.progress is None else f"frame {self.progress[0]}"
                return (
                    f"start phase: {at} after start_timeout_s = {g.start_timeout_s:g} s "
                    f"(the run phase begins at frame {START_FRAMES})"
                )
            return None
        if plant_done or self.progress[0] >= self.progress[1] - 1:
            return None
        frames = list(self._frames)  # a copy: the output thread appends to it meanwhile
        if not frames:
            return None
        t0, k0 = frames[0]
        if now - t0 < g.stall_timeout_s:
            return None  # not a whole window yet
        # frames over the window [now - stall_timeout_s, now]: the newest progress mark at
        # or before the window's start (marks come every progress_interval_s with frames)
        k_then = k0
        for t, k in frames:
            if t <= now - g.stall_timeout_s:
                k_then = k
        n = self.progress[0] - k_then
        if n >= g.stall_timeout_s:  # at least one frame per second of wall time
            return None
        return (
            f"run phase: {n} frames in the last stall_timeout_s = {g.stall_timeout_s:g} s of "
            f"wall time (at frame {self.progress[0]})"
        )

    def stop(self, timeout: float | None = None) -> None:
        """SIGINT every live process, then SIGTERM, then SIGKILL; processes holding a
        recorder only once the others have ended (the bag gets their last messages).  A
        process stopped with SIGSTOP is continued first, so it can stop cleanly."""
        with self._spawn_lock:
            self.stopping = True
        self.signal_all(signal.SIGCONT)
        timeout = self.g.stop_timeout_s if timeout is None else timeout
        first = [p for p in self.procs if not p.has_recorder]
        last = [p for p in self.procs if p.has_recorder]
        self._stop_group(first, timeout)
        self._hand_counts(first, last)
        self._stop_group(last, timeout)
        for p in self.procs:
            p.process.wait()

    def _stop_directory(self) -> Path:
        """The run's directory of counts files (removed when the run ends)."""
        if self._stop_dir is None:
            import tempfile

            self._stop_dir = Path(tempfile.mkdtemp(prefix="fluxdrive-stop-"))
        return self._stop_dir

    def _counts_file(self, p: Proc) -> Path:
        """Where the recorder of process `p` finds the published counts on a stop."""
        return self._stop_directory() / f"{p.name}.json"

    def _hand_counts(self, stopped: list[Proc], recorders: list[Proc]) -> None:
        """Between the two stop groups: every stopped process's `@published` lines read
        (its output pump ends with it), the totals per topic go to each recorder's counts
        file, so it finalises once it has them all (fluxdrive_bringup.record.recorder)."""
        for p in stopped:
            if p.reader is not None:
                p.reader.join(timeout=5.0)
        with self.lock:
            counts = dict(self.published)
        for p in recorders:
            f = self._counts_file(p)
            tmp = f.with_suffix(".tmp")
            tmp.write_text(json.dumps(counts))
            tmp.replace(f)  # whole or not at all when the recorder reads it

    def _stop_group(self, group: list[Proc], timeout: float) -> None:
        self.signal_all(signal.SIGINT, group)
        for sig, wait in ((signal.SIGTERM, timeout), (signal.SIGKILL, 5.0)):
            t_end = time.monotonic() + wait
            while time.monotonic() < t_end and any(p.process.poll() is None for p in group):
                time.sleep(0.05)
            alive = [p for p in group if p.process.poll() is None]
            if not alive:
                break
            self._emit(
                f"[launch] {', '.join(p.label for p in alive)} still running; "
                f"sending {signal.Signals(sig).name}"
            )
            self.signal_all(sig, alive)

    @staticmethod
    def death_text(p: Proc, code: int) -> str:
        if code < 0:
            try:
                what = f"signal {signal.Signals(-code).name}"
            except ValueError:
                what = f"signal {-code}"
        else:
            what = f"exit code {code}"
        return f"{what}, pid {p.process.pid}"

    def _on_death(self, p: Proc, code: int, now: float) -> bool:
        """A process died while the graph runs: apply its on_death.  True = stop the graph."""
        what = self.death_text(p, code)
        if p.on_death == "restart" and p.restarts < p.max_restarts:
            delay = p.backoff_s * 2**p.restarts
            p.restarts += 1
            self.restarts[p.name] = p.restarts
            p.restart_at = now + delay
            self._emit(
                f"[launch] WARNING: process {p.label} died ({what}); restarting in "
                f"{delay:g} s (restart {p.restarts} of {p.max_restarts})"
            )
            return False
        if p.on_death == "ignore":
            p.done = p.ignored = True
            self.ignored.append(p)
            self._emit(
                f"[launch] WARNING: process {p.label} died ({what}); on_death: "
                f"ignore, the graph runs on without it"
            )
            return False
        p.done = True
        self.failed.append(p)
        why = (
            f"on_death: restart, {p.restarts} restarts used"
            if p.on_death == "restart"
            else "on_death: stop"
        )
        last = p.fatal_line()
        said = f"; its last error: {last}" if last else ""
        self._emit(
            f"[launch] ERROR: process {p.label} died ({what}); stopping the graph ({why}){said}"
        )
        return True

    def wait(self, timeout: float | None = None) -> int:
        """Watch until the graph ends.  Returns 0, or 1 if a process died (named) and its
        policy stopped the graph."""
        t_end = None if timeout is None else time.monotonic() + timeout
        grace_end: float | None = None
        while True:
            now = time.monotonic()
            for p in self.procs:
                if p.done:
                    continue
                if p.restart_at is not None:
                    self._restart_when_due(p, now)
                    continue
                code = p.process.poll()
                if code is None:
                    continue
                p.code = code
                if code != 0 and not self.stopping:
                    if self._on_death(p, code, now):
                        self.stop()
                        self._join()
                        return 1
                    continue
                p.done = True
                if (
                    code == 0
                    and any(n.required for n in p.nodes)
                    and not self.stopping
                    and grace_end is None
                ):
                    # the others usually end by themselves (/drive/done); give them time
                    # to drain (the recorder) before stopping them
                    grace_end = time.monotonic() + self.g.stop_grace_s
            if (
                grace_end is not None
                and time.monotonic() > grace_end
                and not self.stopping
                and not all(p.done for p in self.procs)
            ):
                req = [p for p in self.procs if any(n.required for n in p.nodes)]
                self._emit(f"[launch] required process {req[0].label} finished; stopping the graph")
                self.stop()
            if all(p.done for p in self.procs):
                break
            why = self._stuck()
            if why is not None:
                self._emit(f"[launch] ERROR: the graph is stuck ({why}); stopping it")
                self.stop()
                self._join()
                return 1
            if t_end is not None and time.monotonic() > t_end:
                self.timed_out = True
                self._emit("[launch] timeout; stopping the graph")
                self.stop()
                self._join()
                return 1
            time.sleep(0.05)
        self._join()
        bad = [
            p for p in self.procs if p.code not in (0, None) and not self.stopping and not p.ignored
        ]
        return 1 if bad else 0

    def failure_text(self) -> str:
        """'; <process>: <its fatal line>' of the first process whose death stopped the
        graph ('' when none did): for a command's closing line."""
        for p in self.failed:
            last = p.fatal_line()
            if last:
                return f"; {p.label}: {last}"
        return ""

    def _restart_when_due(self, p: Proc, now: float) -> None:
        """A process waiting for its restart: restarted once its back-off is over (never
        while the graph stops)."""
        if self.stopping:
            p.restart_at = None
            p.done = True
        elif p.restart_at is not None and now >= p.restart_at:
            with self._spawn_lock:
                if self.stopping:
                    return
                p.restart_at = None
                self._spawn(p)
            self._emit(
                f"[launch] process {p.label} restarted (pid "
                f"{p.process.pid}, restart {p.restarts} of {p.max_restarts})"
            )

    def _stuck(self) -> str | None:
        """Why the graph is stuck (with the process silent longest and the last warning),
        None while it is not."""
        why = self.stalled(time.monotonic())
        if why is None:
            return None
        live = [p for p in self.procs if not p.done]
        quiet = min(live, key=lambda p: p.t_last_line) if live else None
        if quiet is not None:
            why += (
                f"; silent longest: process {quiet.label} "
                f"({time.monotonic() - quiet.t_last_line:.1f} s)"
            )
        last = f"; last warning: {self.last_warning}" if self.last_warning else ""
        return why + last

    def _join(self) -> None:
        for p in self.procs:
            if p.reader:
                p.reader.join(timeout=5.0)
        if self._progress_shown and self.tty:
            sys.stderr.write("\n")
            self._progress_shown = False

    def run(self, timeout: float | None = None) -> int:
        """start + wait, with Ctrl-C/SIGTERM turned into a clean stop."""
        interrupted = threading.Event()

        def on_signal(signum, frame):  # noqa: ARG001
            if interrupted.is_set():
                self.signal_all(signal.SIGKILL)
                return
            interrupted.set()
            self.interrupted = True
            self.stop_signal = signum
            self._emit(f"[launch] {signal.Signals(signum).name}: stopping the graph")
            threading.Thread(target=self.stop, daemon=True).start()

        old = {}
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                old[s] = signal.signal(s, on_signal)
        try:
            self.start()
            code = self.wait(timeout)
        finally:
            for s, h in old.items():
                signal.signal(s, h)
        self.check_recorded()
        self._bag_hints()
        if self._stop_dir is not None:
            import shutil

            shutil.rmtree(self._stop_dir, ignore_errors=True)
        if interrupted.is_set():
            dirty = [p for p in self.procs if p.code not in (0, None)]
            for p in dirty:
                self._emit(f"[launch] process {p.label} ended with code {p.code} on stop")
            # stopped cleanly by a signal: 128 + its number, as a shell reports it (130 for
            # Ctrl-C, 143 for SIGTERM), so a script can tell a stop from a finished run
            return 1 if dirty else 128 + int(self.stop_signal)
        return code

    def _bag_hints(self) -> None:
        """Name every bag a recorder opened but did not finalise (killed with its writer,
        disk full) and the command that recovers it."""
        for p in self.procs:
            if (
                p.bag_open
                and Path(p.bag_open).is_dir()
                and not (Path(p.bag_open) / "metadata.yaml").exists()
            ):
                self._emit(
                    f"[launch] bag {p.bag_open} was not finalised (process {p.label} "
                    f"ended with code {p.code}); recover it with: ./fluxdrive bag "
                    f"recover {p.bag_open}"
                )


def add_scope(
    g: Graph,
    port: int = 8765,
    token: str | None = None,
    exit_on_done: bool = False,
    observers: list[str] | None = None,
) -> None:
    """Add the live scope to a graph: the scope tap (fluxdrive_bringup.view.scope_tap) in the
    plant's process -- so the samples reach it through the intra-process bus, not DDS -- and
    the scope's web server (fluxdrive_bringup.view.scope) as a process of its own."""
    host = next((n for n in g.nodes if n.node == "plant"), None) or next(
        (n for n in g.nodes if n.node), None
    )
    params: dict[str, Any] = {}
    if host is not None:
        sc = node_parameters(host).get("scenario")
        if sc:
            params["scenario"] = str(sc)
    if observers:
        params["observers"] = list(observers)
    g.nodes.append(
        NodeSpec(
            name="scope_tap",
            node="scope_tap",
            process=(host.process or host.name) if host else "scope_tap",
            parameters=params,
        )
    )
    cmd = [
        sys.executable,
        "-m",
        "fluxdrive_bringup.view.scope",
        "--port",
        str(port),
        "--attach-wait",
        "60",
    ]
    if token:
        cmd += ["--token", token]
    if exit_on_done:
        cmd.append("--exit-on-done")
    if g.namespace:  # a command is not remapped: the server is told the drive's namespace
        cmd += ["--namespace", g.namespace]
    g.nodes.append(NodeSpec(name="scope", cmd=cmd, on_death="ignore"))


def launcher_env_discovery(g: Graph) -> str:
    """The discovery range the graph runs with (for the start line), noting an environment
    value that is overridden."""
    env = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "")
    if env and env.upper() != g.discovery_range:
        return (
            f"{g.discovery_range} (ROS_AUTOMATIC_DISCOVERY_RANGE={env} from the environment "
            f"ignored: set discovery_range in the graph file to change it)"
        )
    return g.discovery_range


def main(argv: list[str]) -> int:
    args = _launch_parser().parse_args(argv)
    if args.log_dir is not None:
        check_output(args.log_dir, "--log-dir")
    from fluxdrive_ros.security import precheck

    why = precheck()
    if why:  # every process would fail the same way: say it once, start nothing
        print(f"[launch] {why}", file=sys.stderr)
        return 2
    g = load_graph(args.graph)
    if args.domain_id is not None:
        g.domain_id = args.domain_id
    if args.namespace:
        g.namespace = check_namespace(args.namespace, "--namespace")
    _apply_sets(g, args.set)
    if args.scope:
        add_scope(g, port=args.scope_port)
    g.shared_domain = bool(args.shared_domain)
    if not args.shared_domain:  # a domain no live node uses (or refused, naming them)
        why = _choose_free_domain(g)
        if why:
            print(f"[launch] {why}", file=sys.stderr)
            return 2
    dom_shown = g.domain_id if g.domain_id is not None else os.environ.get("ROS_DOMAIN_ID", "0")
    procs = ", ".join(f"{pn}[{', '.join(m.fqn for m in ms)}]" for pn, ms in g.processes().items())
    disc = launcher_env_discovery(g)
    print(
        f"[launch] graph {g.name}: {procs}; ROS_DOMAIN_ID={dom_shown}, discovery {disc}", flush=True
    )
    return _run_and_report(g, args)


def _launch_parser():

    ap = Parser(prog="fluxdrive launch", description="start a graph described in YAML")
    ap.add_argument("graph", help="graph YAML (path, or a name under config/graphs/)")
    option(ap, "--domain-id", GraphSettings, help="ROS_DOMAIN_ID for every process")
    ap.add_argument("--timeout", type=float, help="stop the graph after this many seconds")
    ap.add_argument(
        "--namespace",
        help="put the whole drive in this ROS namespace (e.g. /bench_a: /bench_a/drive/frame)",
    )
    ap.add_argument("--log-dir", type=Path, help="also write each process's output here")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="override a node parameter (YAML value), e.g. plant.duration_s=0.5",
    )
    ap.add_argument(
        "--scope",
        action="store_true",
        help="also start the live scope (the scope tap in the plant's process and "
        "the web page; see ./fluxdrive scope)",
    )
    option(
        ap,
        "--scope-port",
        ServeOptions,
        "port",
        help="the scope's TCP port (default 8765; 0: any free port)",
    )
    ap.add_argument(
        "--shared-domain",
        action="store_true",
        help="start even if other "
        "nodes live on the ROS domain (by default refused: graphs on one domain "
        "hear each other)",
    )
    return ap


def _apply_sets(g: Graph, sets: list[str]) -> None:
    """--set NODE.PARAM=VALUE (a YAML value) onto the graph's nodes."""
    for item in sets:
        key, _, val = item.partition("=")
        node, _, pname = key.partition(".")
        match = [n for n in g.nodes if n.name == node or n.fqn == node]
        if not match or not pname or not _:
            raise ConfigError(
                f"--set {item!r}: expected NODE.PARAM=VALUE with NODE one of "
                f"{[n.name for n in g.nodes]}"
            )
        value = set_value(item, val)
        for n in match:
            n.parameters[pname] = value


def set_value(item: str, val: str) -> Any:
    """The YAML value of one `--set NODE.PARAM=VALUE` (ConfigError naming the item)."""
    try:
        return yamlio.loads(val)
    except yaml.YAMLError as exc:
        raise ConfigError(
            f"--set {item[:80]!r}: the value is not valid YAML: {yamlio.describe(exc)}"
        ) from None


def _choose_free_domain(g: Graph) -> str:
    """Put the graph on a domain no live node uses; "" or why it is refused (naming them)."""
    from fluxdrive_bringup.launch.domains import choose_domain

    # (the graph's domain_id, else ROS_DOMAIN_ID, else 0 -- where `param set` and
    # `topic echo` from another shell look by default)
    dom, why = choose_domain(
        g.domain_id if g.domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID") or 0),
        "launch",
    )
    if dom is None:
        return why or "no free ROS domain"
    g.domain_id = dom
    return ""


def _run_and_report(g: Graph, args) -> int:
    """Run the graph; then its bags, restarts and the deaths it ignored."""
    launcher = Launcher(g, log_dir=args.log_dir)
    if launcher.clock_topic != "/clock" and not g.namespace:
        print(f"[launch] shared domain: this graph's sim time is on {launcher.clock_topic}")
    code = launcher.run(args.timeout)
    for b in launcher.bags:
        print(f"[launch] bag: {b}")
    if launcher.restarts:
        print("[launch] restarts: " + ", ".join(f"{k} {v}" for k, v in launcher.restarts.items()))
    for p in launcher.ignored:
        print(f"[launch] died and ignored: {p.label} ({launcher.death_text(p, p.code or 0)})")
    return code
