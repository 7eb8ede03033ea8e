"""The keys of a graph file (`./fluxdrive launch GRAPH.yaml`, fluxdrive_bringup.launch.launcher),
each declared once with its unit, range or choices and text (fluxdrive.core.schema): the
launcher checks a graph file by them (`check_keys`: one line naming the file, the node entry
and the key) and the tables of docs/graph.md are generated from them (`./fluxdrive docs
params`, checked by the docs test).

- GraphSettings: the top-level keys;
- NodeEntry: the keys of an entry of `nodes`;
- DeathPolicy: what happens when a process dies, per node entry or as the graph's default.

GraphSettings.domain_id also ranges every command's `--domain-id`, ServeOptions.port the
scope's and the Foxglove bridge's `--port`.  In the engine (no ROS import), so that every
graph package and the docs command read the same fields."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fluxdrive.core import schema
from fluxdrive.core.machine import ConfigError
from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import param

DOC_PAGE = ROOT / "docs" / "graph.md"

ON_DEATH = ("stop", "restart", "ignore")
DISCOVERY_RANGES = ("LOCALHOST", "SUBNET", "SYSTEM_DEFAULT", "OFF")
# the highest ROS domain whose DDS ports (7400 + 250 x domain + offsets) stay below 65536
DOMAIN_ID_MAX = 232


@dataclass(frozen=True)
class DeathPolicy:
    """When a node's process dies (a signal, a non-zero exit): per node entry, or for every
    node as a top-level key."""

    on_death: str = param(
        "stop",
        unit="",
        doc="stop the graph (exit code 1), restart the process (FLUXDRIVE_RESTART_COUNT=n in "
        "its environment) or ignore it (the graph runs on); not restart for a recorder",
        choices=ON_DEATH,
        live=False,
    )
    max_restarts: int = param(
        3, unit="restarts", doc="restart: at most this many, then stop", range=(0, 1000), live=False
    )
    restart_backoff_s: float = param(
        1.0,
        unit="s",
        doc="restart: wait this long before the first restart, doubling for each next one",
        range=(0.0, 3600.0),
        live=False,
    )


@dataclass(frozen=True)
class GraphSettings:
    """The top-level keys of a graph file (plus DeathPolicy's, the graph's defaults)."""

    name: str = param("", unit="", doc="the graph's name (default: the file's name)", live=False)
    description: str = param("", unit="", doc="what the graph is for (not used)", live=False)
    namespace: str = param(
        "",
        unit="",
        doc="the whole drive in this ROS namespace, e.g. /bench_a (or --namespace)",
        live=False,
    )
    discovery_range: str = param(
        "LOCALHOST",
        unit="",
        doc="ROS_AUTOMATIC_DISCOVERY_RANGE of every process, whatever the environment says "
        "(leaving the machine is an explicit choice here; any case)",
        choices=DISCOVERY_RANGES,
        live=False,
    )
    domain_id: int | None = param(
        None,
        unit="-",
        doc="ROS_DOMAIN_ID of every process (unset: the environment's; --domain-id wins); "
        f"{DOMAIN_ID_MAX} the highest whose DDS ports fit",
        range=(0, DOMAIN_ID_MAX),
        kind=int,
        live=False,
    )
    env: dict[str, Any] | None = param(
        None,
        unit="",
        doc="extra environment of every process: NAME: value (a string or a number)",
        kind=dict,
        live=False,
    )
    nodes: list[Any] | None = param(
        None, unit="", doc="the node entries (below), at least one", kind=list, live=False
    )
    stop_timeout_s: float = param(
        15.0,
        unit="s",
        doc="on a stop: SIGTERM, then SIGKILL, this long after the previous signal",
        range=(0.1, 3600.0),
        live=False,
    )
    stop_grace_s: float = param(
        20.0,
        unit="s",
        doc="a required process ended normally: the others get this long to end by themselves",
        range=(0.1, 3600.0),
        live=False,
    )
    start_timeout_s: float = param(
        300.0,
        unit="s",
        doc="a graph with a plant: its first frames must come within this long of the start",
        range=(1.0, 86400.0),
        live=False,
    )
    stall_timeout_s: float = param(
        120.0,
        unit="s",
        doc="a graph with a plant: after the start, at least one frame per second of wall "
        "time over any interval this long, else it is stopped as stuck",
        range=(1.0, 86400.0),
        live=False,
    )


@dataclass(frozen=True)
class NodeEntry:
    """The keys of an entry of `nodes` (plus DeathPolicy's); exactly one of node and cmd."""

    name: str = param(
        "", unit="", doc="node name, unique in its namespace (letters, digits, _)", live=False
    )
    node: str | None = param(
        None,
        unit="",
        doc="plant | observer | controller | recorder | scope_tap | module:Class",
        kind=str,
        live=False,
    )
    cmd: tuple[str, ...] | None = param(
        None, unit="", doc="any other program, started as is", kind=tuple, live=False
    )
    namespace: str = param("", unit="", doc="the node's namespace (observers: /obs)", live=False)
    process: str = param(
        "",
        unit="",
        doc="entries naming the same process share one (one DDS participant, in-process "
        "delivery); default: a process of its own, named after the node",
        live=False,
    )
    params: tuple[str, ...] = param(
        (),
        unit="",
        doc="ros__parameters files (relative to the graph file or the repo)",
        kind=tuple,
        live=False,
    )
    parameters: dict[str, Any] | None = param(
        None, unit="", doc="inline parameter values: they win over the files", kind=dict, live=False
    )
    required: bool = param(
        False, unit="", doc="its process ending (code 0) ends the graph", live=False
    )
    observers_of: str | None = param(
        None,
        unit="",
        doc="a scenario file (relative to the graph file or the repo): this entry stands for "
        "one node per observer the scenario declares, named after it (give no name)",
        kind=str,
        live=False,
    )


@dataclass(frozen=True)
class ServeOptions:
    """The TCP port the browser scope and the Foxglove bridge serve a graph on (`scope
    --port`, `foxglove --port`, `launch/run/tune --scope-port`) and their connection cap
    (`--max-clients`), ranged once."""

    port: int = param(8765, unit="-", doc="TCP port (0: any free port)", range=(0, 65535))
    max_clients: int = param(
        100,
        unit="-",
        doc="open connections at most; the next is refused at once (HTTP 503)",
        range=(1, 10000),
    )


TOP_KEYS = {**schema.specs(GraphSettings), **schema.specs(DeathPolicy)}
NODE_KEYS = {**schema.specs(NodeEntry), **schema.specs(DeathPolicy)}
# free text: a name, a path or a program (the launcher checks what it can)
FREE_TEXT = frozenset({"name", "description", "namespace", "node", "process"})


def check_keys(raw: dict, keys: dict[str, schema.Spec], where: str) -> None:
    """Every key of the mapping `raw` known (else one line listing the known ones) and its
    value what its field accepts (YAML null: the default): ConfigError '<where>: <key> must
    be ...'."""
    bad = sorted(set(raw) - set(keys), key=str)
    if bad:
        raise ConfigError(f"{where}: unknown key(s) {bad}; expected some of {sorted(keys)}")
    for key, v in raw.items():
        if v is not None:
            if key == "discovery_range" and isinstance(v, str):
                v = v.upper()
            schema.check_value(keys[key], v, f"{where}: {key}")


def docs_tables() -> dict[str, str]:
    """{table key: its Markdown table} of docs/graph.md, as the fields say."""
    return {
        key: schema.markdown_table(cls) + "\n"
        for key, cls in (
            ("graph", GraphSettings),
            ("graph.node", NodeEntry),
            ("graph.on_death", DeathPolicy),
        )
    }
