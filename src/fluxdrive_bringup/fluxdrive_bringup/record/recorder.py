"""recorder: every configured topic -> a rosbag2 bag (MCAP storage, version 9) with rosbags.

Subscriptions are raw (the CDR bytes go into the bag untouched, never deserialised), with
the graph's sample QoS (reliable, deep, transient-local: nothing published during discovery
is lost).  In a process shared with the drive nodes, their topics arrive through the
intra-process bus (fluxdrive_ros.intra); from other processes over DDS.

Writing: a callback only appends the framed bytes to a buffer -- the messages of this
process's nodes a block at a time, as one block record (each topic's messages joined as they
came; the writer lays the topics out in step and takes the times from the stamps) -- and a
feeder thread ships the buffer every 20 ms to the bag-writer helper process
(fluxdrive.io.bagwriter: MCAP built in bulk), which runs on the other core.  Every
`flush_interval_s` (0.5 s) the writer closes its open MCAP chunk and flushes the file, so at
most that much (or one 1 MiB chunk, about 0.1 s of a 10 kHz run) is at risk if the recorder
and its writer are killed outright; `./fluxdrive bag recover` rebuilds a valid bag from the
rest.  At start the bag directory
must be new and writable and its file system must have `min_free_mb` free (one-line error
otherwise); a write that fails later (disk full) stops the recording with an error, the
recorder exits 1 and the complete chunks stay recoverable.

The message definitions are embedded (typestore registered from the project's .msg
files), so the bag opens without the package; the run's machine card and observer
configurations go into the metadata (custom_data "fluxdrive", as fluxdrive.io.bagio writes
it), so `./fluxdrive replay` treats graph bags like in-process ones.

Graph identity: only messages of the recorder's own graph are recorded (the graph_id check of
fluxdrive_ros.graph); others are counted and named in the final line.

Topics: `topics` plus /obs/<name>/estimate for every name in `observers`; types from the
graph's conventions (fluxdrive_ros.topics), others discovered from the graph.
Timestamps: `timestamps` = header (default: each message's header stamp, i.e. the sample
instant -- sim time in a lockstep run; /clock by its value) or receive (wall clock at
reception, as ros2 bag record does).

End: on SIGINT/SIGTERM it takes what waits in its readers -- stopped by the launcher, until
it holds what the stopped nodes published (their counts, $FLUXDRIVE_STOP_COUNTS), see
_drain_on_stop -- then the buffer is flushed and the bag finalised (metadata.yaml, MCAP
summary); what is missing is named in the log and the metadata (fluxdrive_missing).
With exit_on_done, after /drive/done = N-1 it waits until every per-sample topic
it has seen has delivered seq N-1 (or nothing arrived for `drain_timeout_s`), then
finalises and exits.  If the recorder alone is killed outright, the writer process still
finalises the bag with everything handed over (at most the last 20 ms are lost); if the
writer dies too (SIGKILL of the process group), see above.
"""

from __future__ import annotations

import json
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
from fluxdrive.core.schema import param
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive.io.bagwriter import BLOCK_PART, MSG_HDR, check_bag_target, pack_json
from fluxdrive.io.messages import message_seq, seq_offset
from fluxdrive_ros.intra import BlockReader, RawSubscription
from fluxdrive_ros.params import P, config_params, declare, input_durability_param
from fluxdrive_ros.runner import FluxNode, main_node, say

import flux_drive_msgs.msg as fm
from fluxdrive_ros import qos, topics

# the domain-wide topics of every ROS graph: the recorder keeps what its own drive's nodes
# published (namespaced drive: names under its namespace; see _own_drive)
DIAGNOSTICS = topics.DIAGNOSTICS  # diagnostic_msgs/DiagnosticArray, every node, 1 Hz
ROSOUT = topics.ROSOUT  # rcl_interfaces/Log: every node's log lines
T_DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
T_LOG = "rcl_interfaces/msg/Log"
# relative names: the recorder's drive namespace (`__ns:=/a` records /a/drive/frame); the
# bag names them as a drive in the root namespace would (/drive/frame), so a namespaced
# drive's bag is the bag of its solo run.  Absolute names are recorded as they are.
DEFAULT_TOPICS = [
    topics.rel(t)
    for t in (
        topics.FRAME,
        topics.TRUTH,
        topics.DUTY,
        topics.CONTROLLER_STATE,
        topics.DONE,
        topics.CLOCK,
        topics.MARKER,
        topics.FAULT,
    )
] + [DIAGNOSTICS, ROSOUT]
_HDR = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")
_REC = MSG_HDR
# messages of this process's nodes reach the recorder in blocks of this many (or what came
# within fluxdrive_ros.intra.BLOCK_WAIT_S), in publish order (fluxdrive_ros.intra.BlockReader)
BLOCK_MESSAGES = 2048
_IOV_MAX = os.sysconf("SC_IOV_MAX")  # the most buffers one write takes


def conventional_type(topic: str) -> str | None:
    known = {
        topics.FRAME: topics.T_FRAME,
        topics.TRUTH: topics.T_TRUTH,
        topics.DUTY: topics.T_DUTY,
        topics.CONTROLLER_STATE: topics.T_STATE,
        topics.CURRENT_REF: topics.T_REFERENCE,
        topics.DONE: topics.T_DONE,
        topics.CLOCK: topics.T_CLOCK,
        topics.MARKER: topics.T_MARKER,
        topics.FAULT: topics.T_FAULT,
        DIAGNOSTICS: T_DIAGNOSTICS,
        ROSOUT: T_LOG,
    }
    if topic in known:
        return known[topic]
    if re.fullmatch(r"/obs/[^/]+/estimate", topic):
        return topics.T_ESTIMATE
    return None


def _has_seq(msgtype: str) -> bool:
    """flux_drive_msgs per-sample types: Header, then `uint64 seq`."""
    return msgtype in (
        topics.T_FRAME,
        topics.T_TRUTH,
        topics.T_DUTY,
        topics.T_STATE,
        topics.T_REFERENCE,
        topics.T_ESTIMATE,
    )


def recorder_params() -> list[P]:
    """The recorder's parameters: what it records, then how it writes."""
    return _what_params() + _writing_params()


@dataclass
class RecorderWhat:
    """The bag, its topics and metadata (`bag_dir` left empty: bags/run-<time now>)."""

    bag_dir: str = param(
        "",
        unit="",
        doc="output bag directory (must not exist yet)",
        live=False,
    )
    topics: tuple[str, ...] = param(
        tuple(DEFAULT_TOPICS),
        unit="",
        doc="topics to record",
        live=False,
    )
    observers: tuple[str, ...] = param(
        (),
        unit="",
        doc="observer names whose /obs/<name>/estimate is recorded",
        live=False,
    )
    timestamps: str = param(
        "header",
        unit="",
        doc="bag time stamps: header (sample instant) or receive (wall clock)",
        choices=("header", "receive"),
        live=False,
    )
    exit_on_done: bool = param(
        True,
        unit="",
        doc="finalise and exit once the run is done and drained",
    )
    drain_timeout_s: float = param(
        3.0,
        unit="s",
        doc="after /drive/done: give up waiting for missing samples after this "
        "long without new messages",
        range=(0.0, 600.0),
    )
    scenario: str = param(
        "",
        unit="",
        doc="scenario of the run: its machine card and observer configurations go"
        " into the bag's metadata (for replay)",
        live=False,
    )
    duration_s: float = param(
        0.0,
        unit="s",
        doc="run length for the metadata (0: the scenario's)",
        range=(0.0, 3600.0),
        live=False,
    )


def _what_params() -> list[P]:
    """The bag, its topics and metadata (the default bag directory named by the time now)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    what = RecorderWhat(bag_dir=str(REPO_ROOT / "bags" / f"run-{stamp}"))
    return [*config_params(what), input_durability_param()]


@dataclass
class RecorderWriting:
    """Chunks, backlog, the stop's drain and the free space it needs."""

    flush_interval_s: float = param(
        0.5,
        unit="s",
        doc="close the open MCAP chunk and flush the bag file this often (bounds "
        "what a killed recorder loses)",
        range=(0.05, 60.0),
    )
    max_backlog_mb: float = param(
        8.0,
        unit="MB",
        doc="messages received but not yet handed to the bag writer are held to "
        "this much; beyond it the recorder's callback waits for the writer "
        "(backpressure: a lockstep graph slows to the disk's speed instead of"
        " growing in memory; also bounds what a SIGKILL loses)",
        range=(0.5, 4096.0),
        live=False,
    )
    stop_drain_timeout_s: float = param(
        10.0,
        unit="s",
        doc="on a stop: wait this long at most for the messages the stopped nodes"
        " published (their counts, from the launcher) before finalising; what"
        " is missing then is named in the log and the bag's metadata",
        range=(0.0, 600.0),
    )
    min_free_mb: float = param(
        100.0,
        unit="MB",
        doc="refuse to start unless the bag's file system has this much free space",
        range=(0.0, 1000000000.0),
        live=False,
    )


def _writing_params() -> list[P]:
    """Chunks, backlog, the stop's drain and the free space it needs."""
    return config_params(RecorderWriting())


class RecorderNode(FluxNode):
    def __init__(self, name: str = "recorder", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        pv = self.pv = declare(self, recorder_params())
        want = [t for t in pv["topics"] if t]
        want += [topics.rel(topics.estimate_topic(o)) for o in pv["observers"] if o]
        # bag topic name -> the name subscribed (relative ones: in this drive's namespace)
        self.sub_name = {
            (t if t.startswith("/") else "/" + t): topics.in_drive(self, t) for t in want
        }
        self.want = list(self.sub_name)
        self.bag_dir = Path(pv["bag_dir"]).resolve()
        free_mb = check_bag_target(self.bag_dir, pv["min_free_mb"])
        self.write_failed = ""
        custom = {}
        if pv["scenario"]:
            custom = self._run_metadata(pv)
        self._start_writer(custom)
        say(f"@bag-open {self.bag_dir}")  # the launcher names it if unfinalised
        self._init_state()
        self._subscribe_all(pv)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._feeder, name="bag-feeder", daemon=True)
        self.thread.start()
        self.get_logger().info(
            f"recording {len(self.want)} topics to {self.bag_dir} ({free_mb:.0f} MB free)"
        )

    def _init_state(self) -> None:
        pv = self.pv
        self.header_ts = pv["timestamps"] == "header"
        self.buf: list[bytes] = []
        # backlog = bytes_in - bytes_out; each counter has one writer thread (callbacks /
        # feeder), so no lock is needed and no update is lost
        self.bytes_in = 0
        self.bytes_out = 0
        self.max_backlog = int(pv["max_backlog_mb"] * 1e6)
        self.holds = 0  # callbacks that waited for the writer
        self.lock = threading.Lock()
        self.conn_ids: dict[str, int] = {}
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.last_seq: dict[str, int] = {}
        self.lost: dict[str, int] = {}  # seq jumps of the per-period topics: lost in transit
        self.sub_topic: dict[str, str] = {}  # subscribed (resolved) name -> bag topic
        self.stop_missing: dict[str, dict[str, int]] = {}  # short at the end of the stop drain
        self.stop_why = "published by the stopped nodes, never received"
        self.unreported: list[str] = []  # launcher gone: processes that did not report
        self.closes_last = True  # fluxdrive_ros.runner: after the nodes that publish
        self._ppid = os.getppid()  # the launcher: gone = every graph process is stopping
        self.last_rx = time.monotonic()
        self.last_ts = 0
        self.done_seq: int | None = None
        self.closed = False
        self.subs: list[RawSubscription] = []
        self.reader = BlockReader(self._on_block, BLOCK_MESSAGES)

    def _subscribe_all(self, pv: dict) -> None:
        """Every wanted topic (those of unknown type once they appear) and the run's end."""
        self.pending = [t for t in self.want if not self._subscribe(t, conventional_type(t))]
        if self.pending:
            self._discover_timer = self.create_timer(0.2, self._discover)
        if pv["exit_on_done"]:
            self.create_subscription(
                fm.RunDone,
                topics.drive_topic(self, topics.DONE),
                self.graph.typed(topics.DONE, self._on_done),
                qos.LATCHED,
            )
            self._done_timer = self.create_timer(0.1, self._check_done)

    # ----------------------------------------------------------------- writer process
    def _start_writer(self, custom: dict) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "fluxdrive.cli.bagwriter"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            bufsize=0,
        )
        if self.proc.stdin is None or self.proc.stdout is None:  # both were asked for: PIPE
            raise RuntimeError("bag writer process started without its pipes")
        self.pipe = self.proc.stdin
        self.pipe_out = self.proc.stdout
        # bag times on a real epoch: sample time + the wall clock at the start (header
        # stamps stay sim time; the offset is recorded in the bag's settings)
        offset = 0 if self.pv["timestamps"] == "receive" else time.time_ns()
        head = {"path": str(self.bag_dir), "custom_data": custom, "epoch_offset_ns": offset}
        self._send([pack_json(b"H", head)])
        line = self.pipe_out.readline().decode().strip()
        if line != "ready":
            self.proc.wait(timeout=10)
            why = (
                line[6:]
                if line.startswith("error ")
                else (f"bag writer exited with {self.proc.returncode}")
            )
            raise ValueError(f"cannot open bag {self.bag_dir}: {why}")

    def _run_metadata(self, pv) -> dict:
        """custom_data as fluxdrive.io.bagio.write_run_bag stores it.  Live parameter changes
        during the run are not reflected there."""
        from types import SimpleNamespace

        from fluxdrive.drive.scenario import load_scenario, scenario_path
        from fluxdrive.io.bagio import META_KEY, _json_default, run_metadata

        sc = load_scenario(scenario_path(pv["scenario"]))
        if pv["duration_s"] > 0:
            sc.duration_s = pv["duration_s"]
        names = [o for o in pv["observers"] if o and o in sc.observers]
        meta = run_metadata(
            SimpleNamespace(scenario=sc, names=names, driving=sc.driving), 0, None, names
        )
        meta["recorded_by"] = "graph"
        meta["graph_id"] = self.graph.id  # replay keeps this graph's messages only
        return {META_KEY: json.dumps(meta, default=_json_default)}

    # ----------------------------------------------------------------- subscriptions
    def _subscribe(self, topic: str, mtype: str | None) -> bool:
        if mtype is None:
            return False
        from fluxdrive_ros.topics import msg_class

        cls = msg_class(mtype)
        cid = len(self.conn_ids) + 1
        self.conn_ids[topic] = cid
        self.types[topic] = mtype
        self.counts[topic] = 0
        with self.lock:  # the connection record goes down the pipe before its messages
            self.buf.append(pack_json(b"C", {"id": cid, "topic": topic, "type": mtype}))
        prof = {
            topics.DONE: qos.LATCHED,
            topics.MARKER: qos.MARKERS,
            topics.FAULT: qos.MARKERS,
            DIAGNOSTICS: qos.WATCH,
            ROSOUT: qos.ROSOUT_READER,
        }.get(topic, qos.reader(self.pv["input_durability"]))
        buf = self.buf
        counts = self.counts
        last = self.last_seq
        rec = _REC.pack
        hdr = _HDR.unpack_from
        has_seq = _has_seq(mtype)
        every_period = mtype in (topics.T_FRAME, topics.T_TRUTH)  # one per seq, no skips
        header_ts = self.header_ts
        stamped = header_ts and (mtype == topics.T_CLOCK or mtype.startswith("flux_drive_msgs/"))

        def cb(data: bytes) -> None:
            if stamped:
                s, ns = hdr(data, 4)
                t = s * 1_000_000_000 + ns
                self.last_ts = t
            elif header_ts:
                t = self.last_ts
            else:
                t = time.time_ns()
            buf.append(rec(b"M", cid, t, len(data)) + data)
            self.bytes_in += len(data) + _REC.size
            if self.bytes_in - self.bytes_out > self.max_backlog:
                self._hold()
            counts[topic] += 1
            if has_seq:
                k = message_seq(data)
                if every_period and k > last.get(topic, k - 1) + 1:
                    self._gap(topic, last[topic], k)
                last[topic] = k
            self.last_rx = time.monotonic()

        if topic in (DIAGNOSTICS, ROSOUT):
            cb = self._own_drive(topic, cls, cb)
        tag = _TopicBlock(self, topic, cid, every_period) if stamped and has_seq else None
        sub = RawSubscription(
            self,
            cls,
            self.sub_name.get(topic, topic),
            cb,
            prof,
            block=self.reader if tag is not None else None,
            block_tag=tag,
        )
        self.subs.append(sub)
        self.sub_topic[sub.topic] = topic
        return True

    def _on_block(self, parts: list[tuple[_TopicBlock, list[bytes]]]) -> None:
        """Messages of this process's nodes (fluxdrive_ros.intra.BlockReader), by topic:
        appended as one block record (fluxdrive.io.bagwriter), each topic's messages as
        they came -- the bag writer lays the topics out in step and takes the times from
        the stamps -- then counted, a topic at a time."""
        table = [b"", _U16.pack(len(parts))]
        items: list[bytes] = []
        for tag, datas in parts:
            tag.add(datas, table, items)
        n = 2 + BLOCK_PART.size * len(parts) + sum(map(len, items))  # after b"B", u32
        table[0] = b"B" + _U32.pack(n)
        buf = self.buf
        buf.append(b"".join(table))
        buf += items
        self.bytes_in += 5 + n
        for tag, datas in parts:
            tag.account(datas)
        if self.bytes_in - self.bytes_out > self.max_backlog:
            self._hold()
        self.last_rx = time.monotonic()

    def _gap(self, topic: str, last: int, k: int) -> None:
        """A per-period topic jumped from seq `last` to `k`: those messages were published
        but never reached this reader (its DDS reader fell further behind than the writer's
        history, or was dropped for a while: a stalled recorder).  Logged once per topic,
        counted for the final line and the bag's metadata."""
        n = k - last - 1
        if topic not in self.lost:
            self.get_logger().warning(
                f"{topic}: seq jumps from {last} to {k}: {n} messages never reached the "
                f"recorder (its reader fell more than the writer's history of "
                f"{qos.SAMPLE_DEPTH} samples behind, or lost its match: a stalled recorder); "
                f"further gaps are counted"
            )
        self.lost[topic] = self.lost.get(topic, 0) + n

    def _own_drive(self, topic: str, cls, cb):
        """/diagnostics and /rosout are shared by every graph on the domain: a recorder of
        a namespaced drive keeps the messages of its drive's nodes (status names and logger
        names under its namespace).  In the root namespace everything is kept (two graphs
        sharing a domain there are told apart by graph_id, which these messages lack)."""
        ns = topics.drive_namespace(self)
        if ns == "/":
            return cb
        from rclpy.serialization import deserialize_message

        prefix, dotted = ns + "/", ns.strip("/").replace("/", ".") + "."

        def mine(data: bytes) -> None:
            m = deserialize_message(data, cls)
            if topic == ROSOUT:
                ok = m.name.startswith(dotted)
            else:
                ok = any(s.name.startswith(prefix) for s in m.status)
            if ok:
                cb(data)

        return mine

    def _discover(self) -> None:
        names = dict(self.get_topic_names_and_types())
        still = []
        for t in self.pending:
            ts = names.get(self.sub_name.get(t, t))
            if ts:
                self._subscribe(t, ts[0])
                self.get_logger().info(f"recording {t} ({ts[0]})")
            else:
                still.append(t)
        self.pending = still
        if not still:
            self._discover_timer.cancel()

    # ----------------------------------------------------------------- feeding the writer
    def _take(self) -> list[bytes]:
        """What the callbacks appended so far (the buffer is left empty)."""
        buf = self.buf
        items = buf[: len(buf)]
        del buf[: len(items)]
        self.bytes_out += sum(map(len, items))
        return items

    def _hold(self) -> None:
        """Backpressure: wait (in the callback, so the executor of this process waits too)
        until the writer has taken the backlog down to half the limit."""
        self.holds += 1
        if self.holds == 1:
            self.get_logger().warning(
                f"bag writer behind by {(self.bytes_in - self.bytes_out) / 1e6:.1f} MB "
                f"(max_backlog_mb {self.max_backlog / 1e6:g}): holding the callbacks until it "
                f"catches up (a lockstep graph slows down; nothing is dropped)"
            )
        while (
            self.bytes_in - self.bytes_out > self.max_backlog // 2
            and not self.closed
            and not self.stop.is_set()
        ):
            time.sleep(0.002)

    def _feeder(self) -> None:
        t_flush = time.monotonic()
        while not self.stop.wait(0.02):
            items = self._take()
            now = time.monotonic()
            if now - t_flush >= self.pv["flush_interval_s"]:
                t_flush = now
                items.append(b"F")  # the writer closes its open chunk: on disk from here on
            if items:
                with self.lock:
                    if self.closed:
                        return
                    try:
                        self._send(items)
                    except OSError as exc:
                        self._writer_failed(exc)
                        return

    def _send(self, items: list[bytes]) -> None:
        """All of `items` down the pipe to the writer, one after the other, in as few
        writes as the system allows (no copy into one buffer first).  A pipe write returns
        early when a signal interrupts it part-way (Ctrl-C, a SIGSTOP/SIGCONT, a profiler
        attaching): a record cut there corrupted the writer's input ("corrupt input (record
        type b'N')", seen under py-spy), so what is left is written again."""
        fd = self.pipe.fileno()
        views: list = list(items)
        i = 0
        while i < len(views):
            n = os.writev(fd, views[i : i + _IOV_MAX])
            while i < len(views) and n >= len(views[i]):
                n -= len(views[i])
                i += 1
            if n:
                views[i] = memoryview(views[i])[n:]

    def _writer_failed(self, exc: OSError) -> None:
        """The bag writer stopped (a write failed: disk full, ...): stop recording, say why
        and what is left, and end this node with exit code 1 (the launcher applies the
        recorder's on_death policy; the rest of the graph is stopped cleanly by default)."""
        self.closed = True
        try:
            out = self.pipe_out.read().decode()
            self.proc.wait(timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            out = ""
        reason = next(
            (ln[6:] for ln in out.splitlines() if ln.startswith("error ")),
            f"bag writer gone ({exc}); {self.bag_dir} may need "
            f"./fluxdrive bag recover {self.bag_dir}",
        )
        self.write_failed = reason
        self.get_logger().error(f"recording stopped: {reason}")
        self.exit_code = 1
        self.finished = True

    # ----------------------------------------------------------------- end of run
    def _on_done(self, msg) -> None:
        self.done_seq = int(msg.seq)

    def _check_done(self) -> None:
        if self.done_seq is None or self.finished:
            return
        seen = [t for t, mt in self.types.items() if _has_seq(mt) and self.counts[t] > 0]
        complete = all(self.last_seq.get(t, -1) >= self.done_seq for t in seen)
        quiet = time.monotonic() - self.last_rx > self.pv["drain_timeout_s"]
        if complete or quiet:
            if not complete:
                short = {
                    t: self.last_seq.get(t, -1)
                    for t in seen
                    if self.last_seq.get(t, -1) < self.done_seq
                }
                self.get_logger().warning(f"finishing without the last samples of {short}")
            self.finished = True

    # ----------------------------------------------------------------- stop drain
    def _take_waiting(self) -> int:
        """Everything already here, into the bag: what the nodes of this process queued
        for it (intra-process) and what waits in its DDS readers."""
        from fluxdrive_ros import intra

        bus = intra.bus()
        n = bus.deliver_queued(self.subs) if bus is not None else 0
        return n + sum(s.take_waiting() for s in self.subs)

    def _short_of(self, expected: dict[str, int]) -> dict[str, dict[str, int]]:
        """Topics (bag names) of which fewer messages arrived than were published."""
        out = {}
        for name, n_pub in expected.items():
            topic = self.sub_topic.get(name)
            if topic is not None and self.counts.get(topic, 0) < n_pub:
                out[topic] = {"recorded": self.counts[topic], "published": n_pub}
        return out

    def _live_publishers(self) -> list[str]:
        """Sample topics that still have a publisher in another process."""
        return [
            self.sub_topic[s.topic]
            for s in self.subs
            if s.sub is not None
            and self.types.get(self.sub_topic[s.topic], "").startswith("flux_drive_msgs/")
            and s.sub.get_publisher_count() > 0
        ]

    def _drain_on_stop(self) -> None:
        """Before finalising: take what the stopped nodes published.  Stopped by the
        launcher (it stops the recorder last and writes the nodes' published counts to
        $FLUXDRIVE_STOP_COUNTS first): until that many have arrived per topic, or a short
        topic has no publisher left (each flushes before it exits, so what has not come
        then never will).  The launcher gone (killed: every graph process got SIGTERM at
        once, see _parent_gone): until each of the graph's other processes has written
        what it published ($FLUXDRIVE_STOP_DIR, _wait_reports), then as with the launcher's
        counts.  Stopped alone: what is waiting.  At
        most stop_drain_timeout_s (a second signal ends it at once); what is missing is
        logged and noted in the bag's metadata."""
        from fluxdrive_ros.runner import STOP_COUNTS_ENV, stop_requests

        expected = _read_counts(os.environ.get(STOP_COUNTS_ENV, ""))
        parent_gone = expected is None and self._parent_gone(0.5 if stop_requests() else 0.05)
        if expected is None and not parent_gone:
            self._take_waiting()
            return
        limit = float(self.pv["stop_drain_timeout_s"])
        t_end = time.monotonic() + limit
        reported: dict[str, int] | None = None
        if expected is None:  # the launcher is gone: the processes say it themselves
            reported = self._wait_reports(t_end)
        cut: list[str] = []
        while True:
            n = self._take_waiting()
            live = self._live_publishers()
            if expected is not None or reported is not None:
                short = self._short_of(expected if expected is not None else reported or {})
                live = [t for t in short if t in live]
            if not live and not n:
                break
            if time.monotonic() >= t_end or stop_requests() > 1:
                cut = live
                break
            if not n:
                time.sleep(0.005)
        self._take_waiting()
        if expected is not None:
            self.stop_missing = self._short_of(expected)
        elif reported is not None:
            self.stop_missing = self._short_of(reported)
            if not self.stop_missing and not cut and not self.unreported:
                self.log(
                    "stop: the launcher is gone; the bag holds every message the graph's "
                    f"processes say they published ({sum(reported.values())} on "
                    f"{len(reported)} topics)"
                )
        if self.stop_missing or cut:
            what = ", ".join(
                f"{t} {v['recorded']} of {v['published']} "
                f"({v['published'] - v['recorded']} missing)"
                for t, v in self.stop_missing.items()
            )
            why = (
                f"{', '.join(cut)} still had a publisher after stop_drain_timeout_s = "
                f"{limit:g} s (a process that did not end)"
                if cut
                else "their publishers are gone"
            )
            self.log(
                f"stop: the bag lacks messages the stopped nodes published: {what or '-'}; {why}",
                "warning",
            )

    def _parent_gone(self, wait_s: float) -> bool:
        """Whether the launcher is gone. A killed launcher's threads die one by one: the
        parent-death signal comes when the thread that started this process dies, and
        until the last one has, this process is a child of another thread of the same
        launcher (the same pid). So a stop signal without the launcher's counts waits up to
        `wait_s` for the parent to change."""
        t_end = time.monotonic() + wait_s
        while os.getppid() == self._ppid and not _dying(self._ppid):
            if time.monotonic() >= t_end:
                return False
            time.sleep(0.01)
        return True

    def _wait_reports(self, t_end: float) -> dict[str, int]:
        """The launcher is gone (killed): every process of the graph got SIGTERM at once.
        Take messages while waiting until each of the graph's other reporting processes has
        written what it published (fluxdrive_ros.runner.report_published: after its readers
        acknowledged every message, so what is not here by then never comes), at most
        until `t_end`; their counts summed by topic. Processes that never report (killed
        too) are named in ``unreported`` and in the log."""
        from fluxdrive_ros.runner import (
            PROCESS_ENV,
            PUBLISHED_SUFFIX,
            REPORTING_ENV,
            STOP_DIR_ENV,
            stop_requests,
        )

        stop_dir = Path(os.environ.get(STOP_DIR_ENV) or "")
        own = os.environ.get(PROCESS_ENV, "")
        names = [n for n in os.environ.get(REPORTING_ENV, "").split(",") if n and n != own]
        got: dict[str, dict[str, int]] = {}
        while True:
            n = self._take_waiting()
            for name in names:
                if name not in got:
                    counts = _read_counts(str(stop_dir / f"{name}{PUBLISHED_SUFFIX}"))
                    if counts is not None:
                        got[name] = counts
            if len(got) == len(names) or time.monotonic() >= t_end or stop_requests() > 1:
                break
            if not n:
                time.sleep(0.005)
        self.unreported = [nm for nm in names if nm not in got]
        if self.unreported:
            self.log(
                f"stop: the launcher is gone and processes {', '.join(self.unreported)} did "
                "not say what they published (killed too, or still stopping): their "
                "messages cannot be checked",
                "warning",
            )
        total: dict[str, int] = {}
        for counts in got.values():
            for topic, n_pub in counts.items():
                total[topic] = total.get(topic, 0) + int(n_pub)
        self.stop_why = "launcher gone: published by the graph's processes, never received"
        return total

    def _note_missing(self) -> None:
        """What the bag lacks and why, in its metadata (custom_data fluxdrive_missing)."""
        from fluxdrive.io.bagio import note_missing

        if self.unreported:
            note_missing(
                self.bag_dir,
                {},
                "recorder: the launcher is gone and processes "
                f"{', '.join(self.unreported)} did not say what they published",
            )
        if self.stop_missing:
            note_missing(
                self.bag_dir,
                self.stop_missing,
                f"recorder: {self.stop_why}",
            )
        if self.lost:
            note_missing(
                self.bag_dir,
                {},
                "recorder: seq gaps, published but never received (the recorder's reader fell "
                "behind the writers' history or lost its match: a stalled recorder)",
                lost_in_transit=self.lost,
            )

    def close(self) -> None:
        if not self.write_failed and not self.closed:
            self._drain_on_stop()
        self.stop.set()
        self.thread.join(timeout=30.0)
        with self.lock:
            if self.write_failed:
                self.log(f"bag {self.bag_dir} not finalised (recording stopped early)", "error")
                return
            if self.closed:
                return
            self.closed = True
            try:
                self._send([*self._take(), b"E"])
                self.pipe.close()
            except OSError:
                pass
        try:
            out = self.pipe_out.read().decode().strip()
            self.proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out = ""
        if self.proc.returncode != 0 or "closed" not in out:
            why = next(
                (ln[6:] for ln in out.splitlines() if ln.startswith("error ")),
                f"bag writer failed (exit {self.proc.returncode}); {self.bag_dir} may "
                f"be incomplete: ./fluxdrive bag recover {self.bag_dir}",
            )
            self.log(why, "error")
            self.exit_code = 1
        total = sum(self.counts.values())
        detail = ", ".join(f"{t} {c}" for t, c in self.counts.items())
        held = (
            f"; the writer's backpressure held the callbacks {self.holds} times"
            if self.holds
            else ""
        )
        foreign = f"; not recorded: {self.graph.summary()}" if self.graph.foreign else ""
        lost = (
            "; never received (seq gaps): " + ", ".join(f"{t} {n}" for t, n in self.lost.items())
            if self.lost
            else ""
        )
        self.log(f"bag {self.bag_dir} finalised: {total} messages ({detail}){held}{foreign}{lost}")
        self._note_missing()
        say(f"@bag {self.bag_dir}")


def _dying(pid: int) -> bool:
    """Whether process `pid` is gone or on its way: no longer there, a zombie (its main
    thread dead), or a SIGKILL pending for it (Linux /proc; False where unreadable)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True
    except OSError:
        return False
    fields = dict(ln.split(":", 1) for ln in status.splitlines() if ":" in ln)
    if fields.get("State", "").strip()[:1] in ("Z", "X"):
        return True
    try:
        return bool(int(fields.get("ShdPnd", "0").strip(), 16) & (1 << (signal.SIGKILL - 1)))
    except ValueError:
        return False


def _read_counts(path: str) -> dict[str, int] | None:
    """The launcher's published counts {topic: n} (None: no file, not stopped by it)."""
    if not path:
        return None
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(raw, dict):
        return None
    return {str(t): int(n) for t, n in raw.items() if isinstance(n, int)}


class _TopicBlock:
    """One recorded topic's part of a block (RecorderNode._on_block): its part of the block
    record, and the bookkeeping the per-message callback does, once per block."""

    def __init__(self, rec: RecorderNode, topic: str, cid: int, every_period: bool):
        self.rec, self.topic, self.cid = rec, topic, cid
        self.every_period = every_period
        self.raw = b""  # the messages of the last block, back to back
        self.size = 0  # of each of them (0: several sizes)
        self.views: dict[tuple[int, int], np.dtype] = {}  # (seq offset, size) -> frame_id, seq

    def add(self, datas: list[bytes], table: list[bytes], items: list[bytes]) -> None:
        """The messages into the block record: the table entry to `table`, the sizes if
        several and the messages to `items`."""
        n, size = len(datas), len(datas[0])
        self.raw = raw = b"".join(datas)
        if len(set(map(len, datas))) != 1:
            size = 0
            items.append(struct.pack(f"<{n}I", *map(len, datas)))
        table.append(BLOCK_PART.pack(self.cid, n, size))
        items.append(raw)
        self.size = size

    def account(self, datas: list[bytes]) -> None:
        """Counts, the newest stamp, the last seq and the seq gaps (a topic with one message
        per period: a seq more than one past the one before it)."""
        rec, topic = self.rec, self.topic
        last = datas[-1]
        s, ns = _HDR.unpack_from(last, 4)
        rec.last_ts = max(rec.last_ts, s * 1_000_000_000 + ns)
        rec.counts[topic] += len(datas)
        k = message_seq(last)
        if self.every_period:
            prev = rec.last_seq.get(topic)
            if prev is None or k - prev != len(datas) or not self._in_a_row(datas, prev):
                for q in map(message_seq, datas):
                    if prev is not None and q > prev + 1:
                        rec._gap(topic, prev, q)
                    prev = q
        rec.last_seq[topic] = k

    def _in_a_row(self, datas: list[bytes], prev: int) -> bool:
        """The seqs prev + 1, prev + 2, ... (read in one numpy pass when the messages have
        one size and one frame_id)."""
        size, first = self.size, datas[0]
        if not size:
            return False
        off = seq_offset(first)
        dt = self.views.get((off, size))
        if dt is None:
            dt = self.views[(off, size)] = np.dtype(
                {
                    "names": ["flen", "seq"],
                    "formats": ["<u4", "<u8"],
                    "offsets": [12, off],
                    "itemsize": size,
                }
            )
        v = np.frombuffer(self.raw, dt)
        return bool((v["flen"] == v["flen"][0]).all()) and bool(
            (v["seq"] == np.arange(prev + 1, prev + 1 + len(datas), dtype=np.uint64)).all()
        )


def main(argv: list[str] | None = None) -> int:
    return main_node("fluxdrive_bringup.record.recorder:RecorderNode", "recorder", argv)


if __name__ == "__main__":
    sys.exit(main())
