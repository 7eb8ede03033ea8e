"""Rate-limited /diagnostics (diagnostic_msgs/DiagnosticArray) shared by the fluxdrive nodes.

A node registers one or more status sources, each a function returning (level, message,
{key: value}); a wall-clock timer publishes all of them every `diagnostics_period_s`
(default 1 s, declared by each node through `PARAM`).  Counters are cumulative since the
node started; the level says whether they grew since the previous report:

  OK     nothing wrong since the previous report
  WARN   bad / stale / missing / rejected inputs since the previous report (handled)
  ERROR  the node is in a safe state (latched fault, PWM off) or its input is unusable

Status names are "<node>: <what>", e.g. "/obs/flux_measured: input", "/controller:
position source".  The array's stamp is the wall clock (diagnostics are about the process,
not the simulated drive).  Tools: `./fluxdrive topic echo /diagnostics`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from fluxdrive.core.schema import param as schema_param
from fluxdrive.io.topics import DIAGNOSTICS, OFFERED_QOS
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .params import P, config_params

TOPIC = DIAGNOSTICS
OK, WARN, ERROR = 0, 1, 2  # DiagnosticStatus.level (a byte in the message)
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}
QOS = QoSProfile(
    depth=OFFERED_QOS[DIAGNOSTICS][0],  # what bags record as offered (one definition)
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.VOLATILE,
)

Source = Callable[[], tuple[int, str, dict[str, Any]]]


@dataclass
class DiagnosticsSettings:
    """How often a node reports on /diagnostics."""

    diagnostics_period_s: float = schema_param(
        1.0,
        unit="s",
        doc="period of this node's /diagnostics status (0: none)",
        range=(0.0, 60.0),
        live=False,
    )


def param(default_s: float = 1.0) -> P:
    """The `diagnostics_period_s` parameter every node declares."""
    return config_params(DiagnosticsSettings(float(default_s)))[0]


PARAM = param()


def status(
    name: str, level: int, message: str, values: dict[str, Any], hardware_id: str = ""
) -> DiagnosticStatus:
    st = DiagnosticStatus()
    st.name = name
    st.level = bytes([level])
    st.message = message
    st.hardware_id = hardware_id
    st.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
    return st


class Diagnostics:
    """Publishes the registered sources on /diagnostics every `period_s` of wall time."""

    def __init__(self, node, period_s: float, hardware_id: str = ""):
        self.node = node
        self.hardware_id = hardware_id
        self.sources: list[tuple[str, Source]] = []
        self.pub = node.create_publisher(DiagnosticArray, TOPIC, QOS)
        self.timer = node.create_timer(period_s, self.publish) if period_s > 0 else None
        self.n_published = 0
        member = getattr(node, "graph", None)
        if member is not None:  # graph identity (fluxdrive_ros.graph): what was dropped
            self._foreign_reported = 0
            self.add("graph", lambda: self._graph_status(member))

    def _graph_status(self, member) -> tuple[int, str, dict[str, Any]]:
        total = member.total()
        values = {
            "graph_id": member.id,
            "foreign_messages": total,
            **{f"foreign {t}": c for t, c in sorted(member.foreign.items())},
        }
        grew, self._foreign_reported = total > self._foreign_reported, total
        if grew:
            return WARN, "messages of another graph on this domain dropped", values
        return (
            OK,
            f"graph_id {member.id}"
            + (f"; {total} foreign messages dropped so far" if total else ""),
            values,
        )

    def add(self, what: str, fn: Source) -> None:
        self.sources.append((f"{self.node.get_fully_qualified_name()}: {what}", fn))

    def statuses(self) -> list[DiagnosticStatus]:
        out = []
        for name, fn in self.sources:
            level, message, values = fn()
            out.append(status(name, level, message, values, self.hardware_id))
        return out

    def publish(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.node.get_clock().now().to_msg()
        arr.status = self.statuses()
        self.pub.publish(arr)
        self.n_published += 1


class Counters:
    """Named counters with 'grew since the last report' for the WARN level."""

    def __init__(self, *names: str):
        self.values: dict[str, int] = {n: 0 for n in names}
        self._reported: dict[str, int] = dict(self.values)

    def __getitem__(self, name: str) -> int:
        return self.values[name]

    def add(self, name: str, n: int = 1) -> None:
        self.values[name] = self.values.get(name, 0) + n

    def set(self, name: str, n: int) -> None:
        self.values[name] = int(n)

    def grew(self, *names: str) -> list[str]:
        """Names (of `names`, default all) whose count grew since the last `report()`."""
        keys = names or tuple(self.values)
        return [k for k in keys if self.values.get(k, 0) > self._reported.get(k, 0)]

    def report(self) -> dict[str, int]:
        """Snapshot for a status's values; marks them reported."""
        self._reported = dict(self.values)
        return dict(self.values)
