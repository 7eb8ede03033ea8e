"""Who may command the drive: an allow-list of node names for the control path.

The graph's command topic /drive/duty (duties and the PWM enable) is obeyed by the plant and
the bench bridge only from the nodes named in their `allowed_commanders` parameter (default
["/controller"]; "*" = anyone); the bridge's /drive/arm and /drive/reset_fault services only
while no node outside the list holds a client of them (a disarm is always obeyed).

How a message is attributed to a node
-------------------------------------
rclpy (Jazzy) hands a subscription callback a message_info with time stamps and sequence
numbers but *not* the publisher's gid (rmw_message_info_t.publisher_gid is not exposed), and
a service callback no caller identity at all; so a message cannot be matched against
`get_publishers_info_by_topic`.  Instead the commanding node signs its messages: the
DutyCommand.commander carries "<node name>#<tag>", tag = the first 16 hex digits of
HMAC-SHA256(graph key, "<node name>|<topic>").  The graph key is FLUXDRIVE_GRAPH_KEY from
the environment: the launcher draws a fresh random one per launch (unless set), so every
process of a graph shares it and a message from another launch -- an old bag played back, a
second graph on the same domain -- does not verify.  Without a key (a node started by hand)
the tag is still computed (empty key) and the list still keeps out publishers that do not
play along (a stray `topic pub`, a test tool), by name.

Limits -- this is a guard against mistakes, not security
---------------------------------------------------------
The mark travels in clear text: anyone who can read /drive/duty on the domain can copy a
valid mark and publish with it while the key is in use; anyone who can read a graph
process's environment has the key.  Parameter services (param set) and the bridge's `armed`
parameter are not covered.  The service check relies on graph discovery, which can lag a
new client by a moment (the request is then refused: fail safe, retry).  Real access
control is DDS-Security (SROS2 enclaves; see docs/safety.md "Access and security").
"""

from __future__ import annotations

import hashlib
import hmac
import os
from collections import Counter
from dataclasses import dataclass
from typing import Any

from fluxdrive.core.schema import param as schema_param
from fluxdrive.io.messages import duty_commander

from .params import P, config_params

KEY_ENV = "FLUXDRIVE_GRAPH_KEY"
ANYONE = "*"
DEFAULT_ALLOWED = ("/controller",)
# the node name of `./fluxdrive fault reset` (fluxdrive_bringup.inspect.commands), the operator's
# tool; the controller obeys ~/reset_fault only from these
DEFAULT_OPERATORS = ("/fluxdrive_operator",)


@dataclass
class AccessSettings:
    """Whose duty commands a node obeys."""

    allowed_commanders: tuple[str, ...] = schema_param(
        DEFAULT_ALLOWED,
        unit="",
        doc="nodes (fully qualified names) whose duty commands -- and arm/reset requests -- "
        "are obeyed; '*' = any publisher (messages must carry the graph's mark, see "
        "fluxdrive_ros.access)",
        live=False,
    )


def param(default: tuple[str, ...] = DEFAULT_ALLOWED) -> P:
    return config_params(AccessSettings(tuple(default)))[0]


def graph_key() -> bytes:
    return os.environ.get(KEY_ENV, "").encode()


def tag(node_fqn: str, topic: str, key: bytes | None = None) -> str:
    k = graph_key() if key is None else key
    return hmac.new(k, f"{node_fqn}|{topic}".encode(), hashlib.sha256).hexdigest()[:16]


def mark(node_fqn: str, topic: str, key: bytes | None = None) -> str:
    """The mark (DutyCommand.commander) a node puts on its commands on `topic`."""
    return f"{node_fqn}#{tag(node_fqn, topic, key)}"


class CommandGuard:
    """Checks the mark of commands on one topic against the allow-list; counts rejections."""

    def __init__(self, allowed: list[str], topic: str, key: bytes | None = None):
        self.allowed = [a for a in allowed if a]
        self.anyone = ANYONE in self.allowed
        self.topic = topic
        self.valid = {mark(n, topic, key).encode() for n in self.allowed if n != ANYONE}
        self.accepted = 0
        self.rejected: Counter[str] = Counter()  # reason -> count
        self.last_rejected = ""
        self._verdicts: dict[bytes, tuple[str, str]] = {}  # mark -> (reason, text), cached
        self._ok_len, self._ok_tail = 0, b""  # the last accepted command's commander field
        self._ok_codec: object = None  # the codec of the last accepted row (accept_codec)

    def accept_raw(self, data: bytes) -> bool:
        """A serialised DutyCommand (its commander field, read without decoding the rest)."""
        if self.anyone:
            self.accepted += 1
            return True
        # the same commander field as the last accepted command (a controller's every
        # command): its tail, from the field on, is the same bytes -- no need to parse it
        tail = self._ok_tail
        if tail and len(data) == self._ok_len and data.endswith(tail):
            self.accepted += 1
            return True
        fid = duty_commander(data)
        if fid in self.valid:
            self.accepted += 1
            self._ok_len, self._ok_tail = len(data), data[-(len(fid) + 5) :]
            return True
        # a flood repeats one mark: its verdict is worked out once
        verdict = self._verdicts.get(fid)
        if verdict is None:
            verdict = self._verdict(fid.decode(errors="replace"))
            if len(self._verdicts) < 1024:
                self._verdicts[fid] = verdict
        self.rejected[verdict[0]] += 1
        self.last_rejected = verdict[1]
        return False

    def accept_codec(self, rc) -> bool:
        """A command handed over as a row by a publisher of this process (fluxdrive_ros.intra:
        `rc` is its RowCodec): the mark is the codec's commander string, the same one
        its bytes would carry."""
        if rc is self._ok_codec:
            self.accepted += 1
            return True
        ok = self.accept_mark(rc.codec.strings.get("commander", ""))
        if ok and not self.anyone:
            self._ok_codec = rc
        return ok

    def accept_mark(self, frame_id: str) -> bool:
        if self.anyone or frame_id.encode() in self.valid:
            self.accepted += 1
            return True
        self._reject(frame_id)
        return False

    def _verdict(self, frame_id: str) -> tuple[str, str]:
        name, sep, _ = frame_id.partition("#")
        if not sep:
            why = "unmarked"
        elif name not in self.allowed:
            why = "not allowed"
        else:
            why = "bad mark"  # right name, wrong key: another launch, an old bag, a forgery
        return why, f"{why}: {frame_id[:60]!r}"

    def _reject(self, frame_id: str) -> None:
        why, text = self._verdict(frame_id)
        self.rejected[why] += 1
        self.last_rejected = text

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    def values(self) -> dict[str, Any]:
        return {
            "commands_accepted": self.accepted,
            "commands_rejected": self.n_rejected,
            **{f"rejected_{k.replace(' ', '_')}": v for k, v in sorted(self.rejected.items())},
            "last_rejected": self.last_rejected,
            "allowed_commanders": ",".join(self.allowed),
        }


def node_fqn(name: str, namespace: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def service_clients(node, service: str) -> list[str]:
    """Nodes that hold a client of `service` (graph discovery; may lag a new client)."""
    out = []
    for name, ns in node.get_node_names_and_namespaces():
        try:
            svcs = node.get_client_names_and_types_by_node(name, ns)
        except Exception:  # noqa: BLE001 - the node vanished meanwhile
            continue
        if any(s == service for s, _ in svcs):
            out.append(node_fqn(name, ns))
    return out


def check_service_caller(
    node, service: str, allowed: list[str], list_name: str = "allowed_commanders"
) -> str | None:
    """None if a request on `service` may be obeyed, else the reason it may not: every node
    with a client of the service must be allowed (rclpy does not say which one called)."""
    if ANYONE in allowed:
        return None
    clients = service_clients(node, service)
    foreign = [c for c in clients if c not in allowed]
    if foreign:
        return (
            f"refused: {', '.join(foreign)} (not in {list_name} {allowed}) holds a "
            f"client of {service}, and a request cannot be attributed to its caller"
        )
    if not clients:
        return f"refused: the caller of {service} is not known to the graph yet (discovery); retry"
    return None
