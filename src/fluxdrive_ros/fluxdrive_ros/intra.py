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

Rows instead of bytes: a node that publishes an engine row (`RawPublisher.publish_row`: a
frame, an estimate, a duty command) hands a reader of this process that takes rows
(`RawSubscription(row_callback=...)`) the row itself -- `RowCodec.wire_row`, the very row the
reader's `unpack` would fill from the message (fluxdrive.io.messages), without packing and
unpacking it: rclcpp's intra-process delivery hands over the message, not its serialisation,
too.  Readers that take blocks (the recorder, the shadow observers) get the same messages'
bytes, packed in blocks (`RowCodec.pack_block`, one numpy pass) when `ROW_BLOCK` rows have
come, at the bus's timer tick, or when a node or the recorder asks (`flush_rows`,
`deliver_queued`).  The bytes path stays for everything else: a reader in another process
(DDS), a reader of this process without a row callback, another graph's reader.

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
import traceback
from array import array
from collections import defaultdict, deque
from collections.abc import Callable

BATCH = 256
# rows a publisher keeps for the block readers of its topic before packing them (at most
# this many, or one block timer tick)
ROW_BLOCK = 256
# a block subscriber's messages wait at most this long (wall time) for the block to fill
BLOCK_WAIT_S = 0.02


def enabled() -> bool:
    return os.environ.get("FLUXDRIVE_INTRA_PROCESS", "1") not in ("0", "false", "no", "off")


class _Slot:
    """The messages of one subscription waiting in its BlockReader."""

    __slots__ = ("reader", "tag", "items")

    def __init__(self, reader: BlockReader, tag: object):
        self.reader, self.tag = reader, tag
        self.items: list[bytes] = []


class BlockReader:
    """How a node takes the messages of its subscriptions from publishers of this process
    in blocks (Bus.post): `callback(parts)` gets [(tag, datas), ...] -- each subscription's
    messages (tagged by it) in the order they were published -- once `size` have come in
    all, or at most BLOCK_WAIT_S of wall time after the first of them.  One callback per
    block instead of one per message (the recorder: every sample topic; a shadow observer:
    its frames)."""

    def __init__(self, callback: Callable[[list], None], size: int):
        self.callback = callback
        self.size = max(1, int(size))
        self.slots: dict[int, _Slot] = {}  # by id of the tag
        self.count = 0  # messages waiting
        self.tick = 0  # the bus's tick when the first message waiting came
        self.deliver = callback  # what the bus's queue entries name

    def slot(self, tag: object) -> _Slot:
        sl = self.slots.get(id(tag))
        if sl is None:
            sl = self.slots[id(tag)] = _Slot(self, tag)
        return sl

    def take(self) -> list[tuple[object, list[bytes]]]:
        """What waits, by subscription; nothing waits afterwards."""
        parts = []
        for sl in self.slots.values():
            if sl.items:
                parts.append((sl.tag, sl.items))
                sl.items = []
        self.count = 0
        return parts


class SharedBlockReader(BlockReader):
    """One BlockReader for several subscriptions of this process that take the same
    messages in blocks of the same size (the shadow observers' frames): the bus collects
    each message once for all of them (one slot, not one per subscriber, on a topic of every
    PWM period), and each block goes to every callback in turn, in the order they joined,
    as the same list (read it only).  `Bus.shared_reader` gives it by key."""

    def __init__(self, size: int):
        self.callbacks: list[Callable[[list], None]] = []
        super().__init__(self._fan_out, size)

    def _fan_out(self, parts: list) -> None:
        for cb in self.callbacks:
            cb(parts)


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
        # (topic, publisher's graph id) -> (block readers' slots, per-message callbacks)
        self.targets: dict[tuple[str, int], tuple[list[_Slot], list]] = {}
        self.readers: dict[int, BlockReader] = {}  # by id
        self.shared_readers: dict[tuple, SharedBlockReader] = {}
        self.ticks = 0  # of the block timer (BLOCK_WAIT_S / 2)
        self.timer = None
        # bumped whenever a subscription comes: a publisher's cached targets are stale then
        self.gen = 0
        # (topic, publisher's graph id) -> (block readers' slots, row callbacks), or None
        # when a reader of the topic here takes bytes only
        self.row_targets: dict[tuple[str, int], tuple[list[_Slot], list] | None] = {}
        self.row_blocks: list[RowBlocks] = []  # every publisher's rows kept for block readers

    # ------------------------------------------------------------- registration
    def add_publisher(self, topic: str) -> None:
        self.publishers[topic] += 1
        for s in self.subscriptions.get(topic, []):
            s._drop_dds()

    def add_subscription(self, sub: RawSubscription) -> None:
        self.callbacks[sub.topic].append(sub.callback)
        self.subscriptions[sub.topic].append(sub)
        self.targets.clear()
        self.row_targets.clear()
        self.gen += 1
        if sub.block is not None:
            self.readers[id(sub.block)] = sub.block
            if self.timer is None:
                self._start_timer(sub.node)

    def shared_reader(self, key: tuple, callback: Callable[[list], None], size: int):
        """The SharedBlockReader of `key` (what its subscriptions have in common: topic,
        graph, block size), with `callback` joined."""
        r = self.shared_readers.get(key)
        if r is None:
            r = self.shared_readers[key] = SharedBlockReader(size)
        r.callbacks.append(callback)
        return r

    def _start_timer(self, node) -> None:
        """The wall-clock tick that hands over blocks waiting longer than BLOCK_WAIT_S."""
        from rclpy.clock import Clock, ClockType

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.timer = node.create_timer(BLOCK_WAIT_S / 2, self._on_tick, clock=steady)

    def targets_of(self, topic: str, graph_id: int) -> tuple[list, list]:
        """((block reader, tag) pairs, per-message callbacks) a publisher of `graph_id` in
        this process delivers `topic` to.  A subscriber that takes blocks (the recorder, a
        shadow observer) and belongs to the publisher's graph has the messages collected
        for it; any other takes each message: unchecked when of the same graph (the usual
        case: every node of a process comes from one launch), else through the graph-id
        filter (fluxdrive_ros.graph) -- the check costs a microsecond per delivery."""
        key = (topic, graph_id)
        t = self.targets.get(key)
        if t is None:
            blocks, singles = [], []
            for s in self.subscriptions.get(topic, []):
                if s.block is not None and s.graph_id in (0, graph_id):
                    sl = s.block.slot(s.block_tag)
                    if sl not in blocks:  # a shared reader's slot: once for them all
                        blocks.append(sl)
                else:
                    singles.append(s.local_callback(graph_id))
            t = self.targets[key] = (blocks, singles)
        return t

    def row_targets_of(self, topic: str, graph_id: int) -> tuple[list, list] | None:
        """(block readers' slots, row callbacks) a publisher of `graph_id` in this process
        hands rows of `topic` to (`RawPublisher.publish_row`) -- or None when a reader of
        the topic here takes bytes only (no row callback, or another graph's: the graph-id
        filter reads the bytes).  Valid while `gen` stays."""
        key = (topic, graph_id)
        if key in self.row_targets:
            return self.row_targets[key]
        blocks: list[_Slot] = self.targets_of(topic, graph_id)[0]
        rows: list[Callable[[tuple], None]] = []
        t: tuple[list, list] | None = (blocks, rows)
        for s in self.subscriptions.get(topic, []):
            if s.block is not None and s.graph_id in (0, graph_id):
                continue  # a block reader: its slot is in `blocks`
            if s.row_callback is None or s.graph_id not in (0, graph_id):
                t = None
                break
            rows.append(s.row_callback)
        self.row_targets[key] = t
        return t

    def flush_rows(self) -> None:
        """Every publisher's rows kept for block readers, packed and handed to them now --
        all of them before any reader's block is handed over, so a block holds the topics
        in step."""
        posted = False
        for rb in self.row_blocks:
            if rb.seqs:
                rb.flush(hand_over=False)
                posted = True
        if posted:
            for r in list(self.readers.values()):
                if r.count >= r.size:
                    self._hand_over(r)

    # ------------------------------------------------------------- delivery
    def post(self, topic: str, data: bytes, graph_id: int = 0) -> None:
        """One message: queued for each per-message subscriber, collected for each block
        reader (BlockReader: handed over when it holds its size, or at most BLOCK_WAIT_S of
        wall time after its first message; in publish order, tagged by subscription)."""
        self.deliver(self.targets_of(topic, graph_id), data)

    def deliver(self, targets: tuple[list, list], data: bytes) -> None:
        """`post` to targets already looked up (`targets_of`, valid while `gen` stays)."""
        blocks, singles = targets
        if singles:
            self.queue.append((singles, data))
            if not self.scheduled:
                self._schedule()
        for sl in blocks:
            sl.items.append(data)
            r = sl.reader
            r.count += 1
            if r.count == 1:
                r.tick = self.ticks
            elif r.count >= r.size:
                self._hand_over(r)

    def post_block(self, topic: str, datas: list[bytes], graph_id: int = 0) -> None:
        """Messages of one publisher in a row (each subscriber sees them in order, as with
        `post` of each)."""
        blocks, singles = self.targets_of(topic, graph_id)
        if singles:
            self.queue.extend((singles, data) for data in datas)
            if not self.scheduled:
                self._schedule()
        self.post_slots(blocks, datas)

    def post_slots(self, blocks: list[_Slot], datas: list[bytes], hand_over: bool = True) -> None:
        """Messages in a row to these block readers' slots only (`post_block`'s part for
        block readers); a full block is handed over unless `hand_over` is false (the
        caller does it once it has posted everything)."""
        for sl in blocks:
            r = sl.reader
            if not r.count:
                r.tick = self.ticks
            sl.items.extend(datas)
            r.count += len(datas)
            if hand_over and r.count >= r.size:
                self._hand_over(r)

    def _hand_over(self, r: BlockReader) -> None:
        self.queue.append(((r.deliver,), r.take()))
        if not self.scheduled:
            self._schedule()

    def _on_tick(self) -> None:
        """Rows kept for block readers are packed and handed to them; blocks whose first
        message came before the previous tick go now (so at most BLOCK_WAIT_S after it)."""
        self.ticks += 1
        self.flush_rows()
        for r in self.readers.values():
            if r.count and r.tick < self.ticks - 1:
                self._hand_over(r)

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

    def deliver_queued(self, subs: list[RawSubscription]) -> int:
        """Hand the messages still queued or collected for these subscriptions to them now
        (not to the others, and without the executor): a node that closes last (the
        recorder) takes what the nodes of its process published before they stopped.
        Returns how many messages it got."""
        self.flush_rows()
        own: set[int] = set()
        for s in subs:
            own.update((id(s.raw_callback), id(s.callback)))
            if s.block is not None:
                own.add(id(s.block.deliver))
                if s.block.count:
                    self._hand_over(s.block)
        n = 0
        while self.queue:
            cbs, data = self.queue.popleft()
            for cb in cbs:
                if id(cb) in own:
                    cb(data)
                    n += sum(len(d) for _, d in data) if isinstance(data, list) else 1
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

    # the count of matched DDS readers is read again every this many publishes, and at
    # once when a reader matches (an rcl call per publish costs about as much as the
    # delivery itself); a reader matched between its match event and the next publish
    # misses nothing: the event makes that publish count again -- and a lockstep graph's
    # plant waits for its readers and then `start_delay_s` before the first frame
    COUNT_EVERY = 64

    def __init__(self, node, msg_cls, topic: str, qos, stamp=None):
        from rclpy.event_handler import PublisherEventCallbacks

        events = PublisherEventCallbacks(matched=self._on_matched)
        self.pub = node.create_publisher(msg_cls, topic, qos, event_callbacks=events)
        self.topic = self.pub.topic_name
        self.bus = bus()
        if self.bus is not None:
            self.bus.add_publisher(self.topic)
        member = getattr(node, "graph", None)
        self.graph_id = int(member.id) if member is not None else 0
        self._count = self.pub.get_subscription_count
        self._n_dds = 0
        self._until_count = 0  # publishes left before the DDS readers are counted again
        self._gen = -1  # the bus's gen when _targets was looked up (-1: none, or not local)
        self._targets: tuple[list, list] = ([], [])
        # publish_row: the row targets (valid with _gen), the stamps of seqs, rows kept for
        # block readers
        self._rows_to: tuple[list, list] | None = None
        self.stamp = stamp  # fluxdrive.io.messages.Stamp (publish_row)
        self._row_blocks: RowBlocks | None = None
        self.n_published = 0  # the launcher checks the bag against it (fluxdrive_ros.runner)
        pubs = getattr(node, "raw_publishers", None)
        if pubs is None:
            pubs = []
            node.raw_publishers = pubs
        pubs.append(self)

    def _on_matched(self, _info) -> None:
        self._until_count = 0

    def publish(self, data: bytes) -> None:
        b = self.bus
        if b is None or self._gen != b.gen or self._until_count <= 1:
            self._send([data], False)
            return
        # the usual case, as `_send` does it: readers in this process, their targets known
        # (the bus's subscriptions unchanged since), the DDS readers not due to be counted
        self.n_published += 1
        self._until_count -= 1
        b.deliver(self._targets, data)
        if self._n_dds:
            self._publish_dds((data,))

    def publish_row(self, rc, row, seq: int, xf: int = 0) -> None:
        """The message `rc.pack(row, seq, *stamp(seq), xf)` (rc: a fluxdrive.io.messages
        RowCodec of this topic's type), as `publish` of it -- but while every reader in this
        process takes rows and none is matched elsewhere, without the bytes: each row
        reader gets (`rc.wire_row(row, seq, xf)`, seq, rc) -- one new row for all of them,
        read it only -- and the block readers the bytes later, packed in blocks."""
        b = self.bus
        rows_to = self._rows_to
        if rows_to is None or b is None or self._gen != b.gen or self._n_dds:
            self._publish_row_bytes(rc, row, seq, xf)
            return
        self.n_published += 1
        self._until_count -= 1
        if self._until_count <= 0:  # DDS readers counted again (as `_send` does)
            self._until_count = self.COUNT_EVERY
            self._n_dds = self._count()
            if self._n_dds:  # one matched elsewhere: this message goes in bytes
                self.n_published -= 1
                self._publish_row_bytes(rc, row, seq, xf)
                return
        slots, cbs = rows_to
        if cbs:
            b.queue.append((cbs, (rc.wire_row(row, seq, xf), seq, rc)))
            if not b.scheduled:
                b._schedule()
        if slots:
            rb = self._row_blocks
            if rb is None:
                rb = self._row_blocks = RowBlocks(b, self.stamp)
            rb.add(slots, rc, row, seq, xf)

    def _publish_row_bytes(self, rc, row, seq: int, xf: int) -> None:
        """publish_row through the bytes (and a look at the bus: may rows go next time?)."""
        sec, nsec = self.stamp(seq)
        self._send([rc.pack(row, seq, sec, nsec, xf)], False)
        b = self.bus
        self._rows_to = None
        if b is not None and self._gen == b.gen and rc.wire_row is not None:
            self._rows_to = b.row_targets_of(self.topic, self.graph_id)

    def flush_rows(self) -> None:
        """The rows kept for block readers, packed and handed to them now -- with every
        other publisher's of the process (Bus.flush_rows: the topics stay in step)."""
        if self._row_blocks is not None and self._row_blocks.seqs:
            self._row_blocks.bus.flush_rows()

    def publish_block(self, datas: list[bytes]) -> None:
        """Several messages in a row (a shadow observer's block of estimates): the same
        messages as `publish` of each, but a subscriber in this process that takes blocks
        (the recorder) gets them in one call."""
        if datas:
            self._send(datas, True)

    def _send(self, datas: list[bytes], block: bool) -> None:
        """To this process's subscribers through the bus, and over DDS when a reader
        elsewhere is matched -- and always when nobody in this process reads the topic, so
        the writer's transient-local history keeps it for a reader that matches late."""
        self.n_published += len(datas)
        if self._row_blocks is not None and self._row_blocks.seqs:
            self._row_blocks.flush()  # the block readers get the messages in order
        b = self.bus
        local = b is not None and bool(b.callbacks.get(self.topic))
        if local:
            assert b is not None
            self._targets, self._gen = b.targets_of(self.topic, self.graph_id), b.gen
            if block:
                b.post_block(self.topic, datas, self.graph_id)
            else:
                b.deliver(self._targets, datas[0])
            self._until_count -= len(datas)
            if self._until_count <= 0:
                self._n_dds = self._count()
                self._until_count = self.COUNT_EVERY
            if not self._n_dds:
                return
        else:
            self._gen = -1
        self._publish_dds(datas)

    def _publish_dds(self, datas) -> None:
        try:
            # rclpy's Publisher.publish of bytes, the handle held once for the whole block
            h = self.pub.handle
            with h:
                for data in datas:
                    h.publish_raw(data)
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


class KeptRows:
    """Rows kept to go out later as one block of messages (BlockSender, RowBlocks): `keep`
    runs every PWM period, so it keeps as little as it can -- the row's bytes (float64, the
    engine's rows; a copy, the caller reuses its row), the seq and the extra status bits in
    int64 arrays -- and `take` packs them in one numpy pass (RowCodec.pack_block: the bytes
    `pack` gives one by one)."""

    def __init__(self, stamp):
        self.stamp = stamp  # fluxdrive.io.messages.Stamp of the seqs
        self.rows: list[bytes] = []
        self.seqs = array("q")
        self.xfs = array("q")
        self.codec = None  # the RowCodec of the rows kept

    def keep(self, row, seq: int, xf: int) -> int:
        """Keep a row; how many are kept now."""
        self.rows.append(row.tobytes())
        self.xfs.append(xf)
        seqs = self.seqs
        seqs.append(seq)
        return len(seqs)

    def take(self) -> list[bytes]:
        """The messages of the rows kept; none are kept afterwards."""
        import numpy as np

        seqs = self.seqs
        if not seqs or self.codec is None:
            return []
        raw, xfs = b"".join(self.rows), self.xfs
        self.rows, self.seqs, self.xfs = [], array("q"), array("q")
        rows = np.frombuffer(raw, dtype=np.float64).reshape(len(seqs), -1)
        ks = np.frombuffer(seqs, dtype=np.int64)
        xf = np.frombuffer(xfs, dtype=np.int64)
        return self.codec.pack_block(rows, ks, self.stamp.ns_block(ks), xf)


class RowBlocks(KeptRows):
    """The rows a publisher hands to the block readers of this process (the recorder, the
    shadow observers) as messages, posted to the readers' slots -- every publisher's at
    once when one holds ROW_BLOCK rows (so the topics reach a reader in step), at the bus's
    tick, when the codec or the readers change, and before the publisher sends bytes (so
    they come in order)."""

    def __init__(self, bus: Bus, stamp):
        super().__init__(stamp)
        self.bus = bus
        self.slots: list[_Slot] = []
        bus.row_blocks.append(self)

    def add(self, slots: list[_Slot], rc, row, seq: int, xf: int) -> None:
        if rc is not self.codec or slots is not self.slots:
            self.flush()
            self.codec, self.slots = rc, slots
        if self.keep(row, seq, xf) >= ROW_BLOCK:
            # every publisher's rows at once: the topics reach a block reader in step (the
            # recorder lays them out so, and a bag cut short keeps them so)
            self.bus.flush_rows()

    def flush(self, hand_over: bool = True) -> None:
        datas = self.take()
        if datas:
            self.bus.post_slots(self.slots, datas, hand_over)


class BlockSender(KeptRows):
    """Rows of a topic that feeds nothing back in the loop (the plant's truth, the
    controller's state), published in blocks: `add` keeps the row, and every `size` rows
    (or at `flush`: a timer, the end of the run, a stop) they are packed in one numpy pass
    and published as one block -- a subscriber in this process that takes blocks (the
    recorder) gets them in one call, every other reader the same messages, only later.
    Rows of another codec (a ControllerState's fault text is part of its layout) start a
    new block."""

    def __init__(self, pub: RawPublisher, stamp, size: int = 256):
        super().__init__(stamp)
        self.pub = pub
        self.size = size

    def add(self, codec, row, seq: int) -> None:
        if codec is not self.codec:
            self.flush()
            self.codec = codec
        if self.keep(row, seq, 0) == self.size:
            self.flush()

    def flush(self) -> None:
        datas = self.take()
        if datas:
            self.pub.publish_block(datas)


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
        block: BlockReader | None = None,
        block_tag: object = None,
        row_callback: Callable[[tuple], None] | None = None,
    ):
        self.node = node
        # rows from a publisher of this process (RawPublisher.publish_row): (row, seq, codec)
        self.row_callback = row_callback
        # messages of this graph's publishers in this process go to `block` (tagged
        # `block_tag`) instead of `callback`; another graph's come one by one, filtered
        self.block = block
        self.block_tag = block_tag
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
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
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
    # the rcl clock handles themselves: ROSClock.set_ros_time_override and rclpy's Time
    # wrap the same calls in type checks and a context manager each, three times the cost
    # (a composed drive's ten clocks took ~50 us per /clock message that way)
    handles = [n.get_clock().handle for n in sim]
    unpack = _CLOCK.unpack_from
    ros_time = ClockType.ROS_TIME
    time_point = _rclpy.rcl_time_point_t

    def on_clock(data: bytes) -> None:
        sec, nsec = unpack(data, 4)
        t = time_point(sec * 1_000_000_000 + nsec, ros_time)
        for h in handles:
            h.set_ros_time_override(t)

    # what rclpy's TimeSource subscribes with: the newest time is all that matters
    best_effort = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    return RawSubscription(sim[0], Clock, "/clock", on_clock, best_effort)
