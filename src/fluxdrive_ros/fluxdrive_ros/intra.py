"""Intra-process delivery for nodes that share a process (rclpy has none of its own).

rclcpp delivers between nodes of one process without the middleware (intra-process
communication in component containers); rclpy always goes through DDS, which costs about
10 us per delivery plus 5 us per publish here -- most of a 10 kHz period once a frame has six
readers.  This module gives the fluxdrive nodes the same shortcut:

- `RawPublisher.publish(bytes)` hands the CDR bytes to every subscriber of that topic in
  the same process (queued, see below) and publishes them over DDS too if a reader in
  another process is matched (`topic echo`, a recorder elsewhere, a remote controller) or
  if nobody in this process reads the topic (so a late reader still finds the samples in
  the writer's transient-local history);
- `RawSubscription` registers its callback with the process's bus; while the topic has a
  publisher in this process it keeps no DDS subscription (so no message arrives twice),
  otherwise it subscribes over DDS as usual.  Messages of another graph are dropped (and
  counted) before the callback (fluxdrive_ros.graph).

Ordering: deliveries go through one FIFO per process, drained by executor tasks in batches
of `BATCH`; between batches the executor serves everything else (parameter services,
timers, messages from other processes), so a lockstep loop that lives entirely inside one
process still answers `param set` at once.  The bytes are the same CDR either way, so a
graph gives the same numbers with and without intra-process delivery (tests check both).

Limitation: a topic with a publisher in this process is read only from that publisher by
this process's subscribers (one publisher per topic is the graph's convention; a second
publisher of the same topic in another process would not be heard here).
Set FLUXDRIVE_INTRA_PROCESS=0 to switch the shortcut off (everything over DDS).
"""

from __future__ import annotations

import os
import struct
import time
import traceback
from collections import defaultdict, deque
from collections.abc import Callable

BATCH = 256


def enabled() -> bool:
    return os.environ.get("FLUXDRIVE_INTRA_PROCESS", "1") not in ("0", "false", "no", "off")


class Bus:
    def __init__(self):
        self.publishers: dict[str, int] = defaultdict(int)
        self.callbacks: dict[str, list[Callable[[bytes], None]]] = defaultdict(list)
        self.subscriptions: dict[str, list[RawSubscription]] = defaultdict(list)
        self.queue: deque = deque()
        self.scheduled = False
        self.executor = None
        self.error: BaseException | None = None
        self.on_error: Callable[[BaseException], None] | None = None
        self.on_interrupt: Callable[[], None] | None = None
        self.delivered = 0
        self.targets: dict[tuple[str, int], list[Callable[[bytes], None]]] = {}
        self.block_targets: dict[tuple[str, int], tuple[list, list]] = {}

    # ------------------------------------------------------------- registration
    def add_publisher(self, topic: str) -> None:
        self.publishers[topic] += 1
        for s in self.subscriptions.get(topic, []):
            s._drop_dds()

    def add_subscription(self, sub: RawSubscription) -> None:
        self.callbacks[sub.topic].append(sub.callback)
        self.subscriptions[sub.topic].append(sub)
        self.targets.clear()
        self.block_targets.clear()

    def targets_of(self, topic: str, graph_id: int) -> list[Callable[[bytes], None]]:
        """The callbacks a publisher of `graph_id` in this process delivers `topic` to: a
        subscriber of the same graph (the usual case: every node of a process comes from one
        launch) takes the bytes unchecked; any other gets the graph-id filter
        (fluxdrive_ros.graph) -- the check costs a microsecond per delivery, a few dozen of
        them per PWM period."""
        key = (topic, graph_id)
        cbs = self.targets.get(key)
        if cbs is None:
            cbs = [s.local_callback(graph_id) for s in self.subscriptions.get(topic, [])]
            self.targets[key] = cbs
        return cbs

    def block_targets_of(self, topic: str, graph_id: int) -> tuple[list, list]:
        """(the block callbacks, the per-message callbacks) a block of `topic` from a
        publisher of `graph_id` goes to: a subscriber that takes blocks (the recorder) gets
        the whole block in one call, the others each message."""
        key = (topic, graph_id)
        t = self.block_targets.get(key)
        if t is None:
            blocks, singles = [], []
            for s in self.subscriptions.get(topic, []):
                cb = s.local_block_callback(graph_id)
                if cb is not None:
                    blocks.append(cb)
                else:
                    singles.append(s.local_callback(graph_id))
            t = self.block_targets[key] = (blocks, singles)
        return t

    # ------------------------------------------------------------- delivery
    def post_block(self, topic: str, datas: list[bytes], graph_id: int) -> None:
        """Messages of one publisher in a row: one queue entry per block subscriber, one
        per message for the others (each subscriber sees them in order, as with `post`)."""
        blocks, singles = self.block_targets_of(topic, graph_id)
        q = self.queue
        for cb in blocks:
            q.append(((cb,), datas))
        if singles:
            for data in datas:
                q.append((singles, data))
        if (blocks or singles) and not self.scheduled:
            self._schedule()

    def post(self, topic: str, data: bytes, graph_id: int | None = None) -> None:
        cbs = self.callbacks.get(topic) if graph_id is None else self.targets_of(topic, graph_id)
        if not cbs:
            return
        self.queue.append((cbs, data))
        if not self.scheduled:
            self._schedule()

    def _schedule(self) -> None:
        if self.executor is None:  # not spinning yet: delivered once spinning starts
            return
        self.scheduled = True
        self.executor.create_task(self._drain)

    def start(self, executor) -> None:
        self.executor = executor
        if self.queue and not self.scheduled:
            self._schedule()

    def _drain(self) -> None:
        self.scheduled = False
        q = self.queue
        n = 0
        try:
            while q and n < BATCH:
                cbs, data = q.popleft()
                for cb in cbs:
                    cb(data)
                n += 1
        except KeyboardInterrupt:  # Ctrl-C while a callback ran: a stop, not an error
            if self.on_interrupt:
                self.on_interrupt()
            return
        except BaseException as exc:  # noqa: BLE001 - report through the runner
            traceback.print_exc()
            self.error = exc
            if self.on_error:
                self.on_error(exc)
            return
        finally:
            self.delivered += n
        if q and not self.scheduled:
            self._schedule()

    def deliver_queued(self, callbacks: list[Callable[[bytes], None]]) -> int:
        """Hand the messages still queued to these callbacks only (not to the others, and
        without the executor): a node that closes last (the recorder) takes what the nodes
        of its process published before they stopped.  Returns how many it got."""
        own = {id(cb) for cb in callbacks}
        n = 0
        while self.queue:
            cbs, data = self.queue.popleft()
            for cb in cbs:
                if id(cb) in own:
                    cb(data)
                    n += 1
        return n


_BUS: Bus | None = None


def bus() -> Bus | None:
    """The process's bus (None when intra-process delivery is off)."""
    global _BUS
    if _BUS is None and enabled():
        _BUS = Bus()
    return _BUS


class RawPublisher:
    """A publisher of serialised messages with intra-process delivery."""

    # how long the count of matched DDS readers is reused (an rcl call per publish costs
    # about as much as the delivery itself); a reader matched meanwhile misses at most what
    # was published in that much wall time -- never a sample of a lockstep graph, whose
    # plant waits for its readers and then `start_delay_s` before the first frame
    COUNT_REUSE_S = 0.001

    def __init__(self, node, msg_cls, topic: str, qos):
        self.pub = node.create_publisher(msg_cls, topic, qos)
        self.topic = self.pub.topic_name
        self.bus = bus()
        if self.bus is not None:
            self.bus.add_publisher(self.topic)
        self._post = self.bus.post if self.bus is not None else None
        member = getattr(node, "graph", None)
        self.graph_id = int(member.id) if member is not None else 0
        self._count = self.pub.get_subscription_count
        self._n_dds = 0
        self._t_count = -1.0
        self._publish = self.pub.publish
        self.n_published = 0  # the launcher checks the bag against it (fluxdrive_ros.runner)
        pubs = getattr(node, "raw_publishers", None)
        if pubs is None:
            pubs = []
            node.raw_publishers = pubs
        pubs.append(self)

    def _dds_readers(self) -> int:
        now = time.perf_counter()
        if now - self._t_count >= self.COUNT_REUSE_S:
            self._n_dds = self._count()
            self._t_count = now
        return self._n_dds

    def publish(self, data: bytes) -> None:
        self.n_published += 1
        local = False
        if self._post is not None and self.bus is not None:
            local = bool(self.bus.callbacks.get(self.topic))
            if local:
                self._post(self.topic, data, self.graph_id)
        # over DDS when a reader elsewhere is matched -- and always when nobody in this
        # process reads the topic, so the writer's transient-local history keeps it for
        # a reader that matches late
        if not local or self._dds_readers():
            self._publish_dds((data,))

    def publish_block(self, datas: list[bytes]) -> None:
        """Several messages in a row (a shadow observer's block of estimates): the same
        messages as `publish` of each, but a subscriber in this process that takes blocks
        (the recorder) gets them in one call."""
        if not datas:
            return
        self.n_published += len(datas)
        local = False
        if self.bus is not None:
            local = bool(self.bus.callbacks.get(self.topic))
            if local:
                self.bus.post_block(self.topic, datas, self.graph_id)
        if not local or self._dds_readers():
            self._publish_dds(datas)

    def _publish_dds(self, datas) -> None:
        try:
            for data in datas:
                self._publish(data)
        except Exception:
            import rclpy

            if rclpy.ok():
                raise
            # the context is shutting down (Ctrl-C): messages still in flight are dropped

    @property
    def topic_name(self) -> str:
        return self.topic

    def subscription_count(self) -> int:
        local = len(self.bus.callbacks.get(self.topic, ())) if self.bus is not None else 0
        return self.pub.get_subscription_count() + local

    def wait_for_all_acked(self, timeout) -> bool:
        return self.pub.wait_for_all_acked(timeout)


class RawSubscription:
    """A raw (bytes) subscription with intra-process delivery.

    `drain` > 0: when a message arrives over DDS the callback also takes up to `drain` more
    that are already waiting in the reader, straight from it.  Through the executor every
    message costs a wait-set round (~100 us in rclpy); taken in a row it costs the take
    and the callback.  A reader that may be flooded (the plant's /drive/duty: foreign
    commands are refused by their mark, in the callback) keeps its loop's deadline so."""

    def __init__(
        self,
        node,
        msg_cls,
        topic: str,
        callback: Callable[[bytes], None],
        qos,
        drain: int = 0,
        block_callback: Callable[[list[bytes]], None] | None = None,
    ):
        self.node = node
        # takes a block of messages of one publisher of this process in one call (else
        # they come one by one); not graph-filtered: used for this graph's publishers only
        self.block_callback = block_callback
        self.msg_cls = msg_cls
        self.qos = qos
        self.topic = node.resolve_topic_name(topic)
        self.raw_callback = callback
        member = getattr(node, "graph", None)  # only this graph's messages reach `callback`
        self.graph_id = int(member.id) if member is not None else 0
        if member is not None and member.carries_id(msg_cls):
            callback = member.filter(self.topic, callback)
        self.callback = callback
        self.drain = drain
        self.bus = bus()
        self.sub = None
        if self.bus is not None:
            self.bus.add_subscription(self)
        if self.bus is None or not self.bus.publishers.get(self.topic):
            dds_cb = self._drained if drain > 0 else callback
            self.sub = node.create_subscription(msg_cls, self.topic, dds_cb, qos, raw=True)

    def local_callback(self, publisher_graph_id: int) -> Callable[[bytes], None]:
        """The callback for bytes from a publisher of this process with that graph id:
        unchecked when it is this node's graph (or this node accepts any), else filtered."""
        if self.graph_id in (0, publisher_graph_id):
            return self.raw_callback
        return self.callback

    def local_block_callback(self, publisher_graph_id: int):
        """The block callback for a publisher of this process with that graph id (None:
        none, or another graph's publisher, whose messages go one by one through the
        filter)."""
        if self.block_callback is not None and self.graph_id in (0, publisher_graph_id):
            return self.block_callback
        return None

    def _drained(self, data: bytes) -> None:
        self.callback(data)
        sub = self.sub
        for _ in range(self.drain):
            if sub is None:
                return
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, True)
            if taken is None:
                return
            self.callback(taken[0])
            sub = self.sub  # the callback may have dropped the DDS reader

    def take_waiting(self) -> int:
        """Hand every message waiting in the DDS reader to the callback now (no executor:
        a stopping node's last take).  Returns how many."""
        n = 0
        while self.sub is not None:
            with self.sub.handle:
                taken = self.sub.handle.take_message(self.sub.msg_type, True)
            if taken is None:
                break
            self.callback(taken[0])
            n += 1
        return n

    def _drop_dds(self) -> None:
        if self.sub is not None:
            self.node.destroy_subscription(self.sub)
            self.sub = None

    def publisher_count(self) -> int:
        local = self.bus.publishers.get(self.topic, 0) if self.bus is not None else 0
        return (self.sub.get_publisher_count() if self.sub is not None else 0) + local


_CLOCK = struct.Struct("<iI")  # rosgraph_msgs/Clock after the CDR header: sec, nanosec


def share_sim_time(nodes) -> RawSubscription | None:
    """One /clock reader for every node of this process that runs on sim time, instead of
    one per node.  rclpy gives each node its own TimeSource with its own DDS subscription
    of /clock: nine nodes of a composed drive took nine DDS deliveries (and deserialisations)
    of every /clock message, about as much CPU as the closed loop's own messages.  Here the
    nodes' subscriptions are dropped and one raw subscription -- through the bus when the
    plant publishes in this process, else over DDS -- sets every node's ROS time from the
    same message.  ROS time of each node stays the newest /clock, as with rclpy's own (a
    node switched to sim time later subscribes on its own again).  The clock topic is the
    one the time sources read (`/clock`, remapped to a namespaced drive's own clock)."""
    from rclpy.clock import ClockType
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.time import Time
    from rosgraph_msgs.msg import Clock

    sim = [n for n in nodes if getattr(n, "_time_source", None) is not None]
    sim = [n for n in sim if n._time_source.ros_time_is_active]
    if not sim:
        return None
    for n in sim:
        ts = n._time_source
        if ts._clock_sub is not None:
            n.destroy_subscription(ts._clock_sub)
            ts._clock_sub = None
    clocks = [n.get_clock() for n in sim]
    unpack = _CLOCK.unpack_from
    ros_time = ClockType.ROS_TIME

    def on_clock(data: bytes) -> None:
        sec, nsec = unpack(data, 4)
        t = Time(seconds=sec, nanoseconds=nsec, clock_type=ros_time)
        for c in clocks:
            c.set_ros_time_override(t)

    # what rclpy's TimeSource subscribes with: the newest time is all that matters
    best_effort = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    return RawSubscription(sim[0], Clock, "/clock", on_clock, best_effort)
