"""Graph identity: which launch a message belongs to, and dropping (and counting) the rest.

Two graphs on one ROS domain hear each other's topics.  Every message a fluxdrive graph
publishes on its per-sample topics, /drive/done and /drive/param_marker carries
`graph_id` (a uint64 right after `seq`; fluxdrive.io.messages.GRAPH_TYPES), and every node
reads only its own graph's:

- the id: the node's read-only parameter `graph_id`.  Its default comes from the launch:
  the launcher draws one random graph key per launch (FLUXDRIVE_GRAPH_KEY, which also signs
  the duty commands, fluxdrive_ros.access) and every process of the graph derives the same id
  from it (`id_from_key`, a one-way hash: the id travels in clear, the key does not).  A node
  started by hand without a key has id 0;
- publishing: the node's codecs pack its id as a constant (fluxdrive.io.messages.RowCodec);
- reading: every raw subscription of a node (fluxdrive_ros.intra.RawSubscription) checks the
  id on the bytes before anything is decoded; a message with another id is dropped and
  counted per topic, the first one logged in one line, the count at the end.  Id 0 in the
  node means "not in a launched graph": it accepts every id (a bridge or tool started by
  hand keeps working as before).  A message with id 0 reaching a node with an id is foreign
  like any other (a stray tool cannot feed a graph) -- except on /drive/param_marker
  (`ZERO_OK_TOPICS`): the operator's scope started outside the launch cannot know the id and
  stamps 0; its markers are accepted by every recorder on the domain.

A bench bridge or bag replay launched as part of a graph gets the graph's key (and so its
id) like every other node; one started by hand into a running graph is given the graph's
id explicitly (`-p graph_id:=<id>`; `./fluxdrive param get /plant graph_id` shows it).
"""

from __future__ import annotations

import hashlib
import os
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from fluxdrive.core.schema import param as schema_param
from fluxdrive.io.messages import GRAPH_TYPES
from fluxdrive.io.topics import MARKER

from .access import KEY_ENV
from .params import P, config_params

MAX_ID = 2**63 - 1  # a ROS integer parameter is int64
# topics on which id 0 (a tool outside any launch) is accepted by a node with an id
ZERO_OK_TOPICS = frozenset({MARKER})
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


def id_from_key(key: str) -> int:
    """The graph id of a launch's graph key: 0 without a key, else 1..2^63-1."""
    if not key:
        return 0
    h = hashlib.sha256(b"fluxdrive graph id|" + key.encode()).digest()
    return (int.from_bytes(h[:8], "little") & MAX_ID) or 1


def env_id() -> int:
    return id_from_key(os.environ.get(KEY_ENV, ""))


# the topics every node of a graph shares with every other ROS node on the domain, whose
# messages carry no graph id: a graph sharing its domain gets its own copy of each
SHARED_TOPICS = ("/clock", "/diagnostics", "/rosout")


def private_topic(graph_id: int, topic: str) -> str:
    """The name `topic` (one of SHARED_TOPICS) has for a graph that shares its ROS domain
    (`--shared-domain`): rosgraph_msgs/Clock, diagnostic_msgs/DiagnosticArray and
    rcl_interfaces/Log carry no graph id, so such a graph publishes and reads them here (the
    launcher remaps each for every node of it)."""
    return f"/fluxdrive/graph_{graph_id:016x}{topic}"


@dataclass
class GraphSettings:
    """The graph a node belongs to."""

    graph_id: int = schema_param(
        0,
        unit="-",
        doc="identity of this node's graph: stamped on every message it publishes; messages "
        "with another id are dropped and counted (0: not in a launched graph, accept any); "
        "default from the launch (FLUXDRIVE_GRAPH_KEY)",
        range=(0, MAX_ID),
        live=False,
    )


def param() -> P:
    return config_params(GraphSettings(env_id()))[0]


def msg_type_of(msg_cls) -> str:
    """'pkg/msg/Name' of a generated rclpy message class."""
    return f"{msg_cls.__module__.split('.')[0]}/msg/{msg_cls.__name__}"


class Membership:
    """A node's graph id and its count of foreign messages (per topic)."""

    def __init__(self, node, graph_id: int):
        self.node = node
        self.id = int(graph_id)
        self.foreign: Counter[str] = Counter()
        self.foreign_ids: set[int] = set()

    def carries_id(self, msg_cls) -> bool:
        return msg_type_of(msg_cls) in GRAPH_TYPES

    def accepts(self, other: int) -> bool:
        return self.id == 0 or other == self.id

    def reject(self, topic: str, other: int) -> None:
        """Count a foreign message; one log line at the first."""
        first = not self.foreign
        self.foreign[topic] += 1
        self.foreign_ids.add(other)
        if first:
            self.node.get_logger().warning(
                f"{topic}: message from another graph (graph_id {other}, this graph's "
                f"{self.id}) ignored; further ones are counted (summary at the end)"
            )

    def filter(self, topic: str, callback: Callable[[bytes], None]) -> Callable[[bytes], None]:
        """`callback` for raw GRAPH_TYPES bytes, called only for this graph's messages."""
        if self.id == 0:
            return callback
        mine = self.id
        zero_ok = any(topic == t or topic.endswith(t) for t in ZERO_OK_TOPICS)
        u32, u64 = _U32.unpack_from, _U64.unpack_from
        reject = self.reject

        def cb(data: bytes) -> None:
            off = 16 + u32(data, 12)[0]  # past the header's frame_id
            off += (-(off - 4)) % 8  # seq, aligned to 8 in the payload; graph_id follows
            gid = u64(data, off + 8)[0]
            if gid == mine or (zero_ok and gid == 0):
                callback(data)
            else:
                reject(topic, gid)

        return cb

    def typed(self, topic: str, callback: Callable) -> Callable:
        """`callback` for deserialised messages with a graph_id field (/drive/done)."""

        def cb(msg) -> None:
            if self.accepts(int(msg.graph_id)):
                callback(msg)
            else:
                self.reject(topic, int(msg.graph_id))

        return cb

    def total(self) -> int:
        return sum(self.foreign.values())

    def summary(self) -> str:
        """One line for the end of the node's life ('' if nothing foreign came)."""
        if not self.foreign:
            return ""
        per = ", ".join(f"{t} {c}" for t, c in sorted(self.foreign.items()))
        ids = ", ".join(str(i) for i in sorted(self.foreign_ids)[:4])
        return (
            f"ignored {self.total()} messages from other graphs ({per}; graph_id "
            f"{ids}{', ...' if len(self.foreign_ids) > 4 else ''})"
        )
