"""recorder: every configured topic -> a rosbag2 bag (MCAP storage, version 9) with rosbags.

Subscriptions are raw (the CDR bytes go into the bag untouched, no deserialisation), with
the graph's sample QoS (reliable, deep, transient-local: nothing published before discovery
completed is lost).  Callbacks only append to a buffer; a writer thread moves the buffer
into the bag, so the executor thread stays free.  The message definitions are embedded
(typestore built from the project's .msg files), so the bag opens without the package.

Topics: `topics` lists names; types come from the graph's naming conventions (see
fluxdrive_ros.topics) or, for other names, from graph discovery (subscribed as soon as the
topic appears).  Timestamps: `timestamps` = header (default: the sample instant in each
message's header, i.e. sim time in a lockstep run; /clock by its value) or receive (wall
clock at reception, as ros2 bag record does).

End: on SIGINT/SIGTERM the buffer is written and the bag finalised (metadata.yaml, MCAP
summary).  With exit_on_done, after /drive/done = N-1 it waits until every per-sample topic
it has seen has delivered seq N-1 (or nothing arrived for `drain_timeout_s`), then
finalises and exits.
"""

from __future__ import annotations

import re
import struct
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

from fluxdrive.scenario import REPO_ROOT
from fluxdrive_ros import qos, topics
from fluxdrive_ros.params import P, declare
from fluxdrive_ros.runner import FluxNode, main_node

from std_msgs.msg import UInt64

from .bagio import typestore

DEFAULT_TOPICS = [topics.FRAME, topics.TRUTH, topics.DUTY, topics.CONTROLLER_STATE,
                  topics.DONE, topics.CLOCK]
_HDR = struct.Struct("<iI")
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")


def conventional_type(topic: str) -> str | None:
    known = {topics.FRAME: topics.T_FRAME, topics.TRUTH: topics.T_TRUTH,
             topics.DUTY: topics.T_DUTY, topics.CONTROLLER_STATE: topics.T_STATE,
             topics.DONE: topics.T_UINT64, topics.CLOCK: topics.T_CLOCK}
    if topic in known:
        return known[topic]
    if re.fullmatch(r"/obs/[^/]+/estimate", topic):
        return topics.T_ESTIMATE
    return None


def _seq_offset(msgtype: str) -> bool:
    return msgtype.startswith("flux_drive_msgs/") and msgtype != "flux_drive_msgs/msg/DriveFault"


class RecorderNode(FluxNode):
    def __init__(self, name: str = "recorder", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        pv = declare(self, [
            P("bag_dir", str(REPO_ROOT / "bags" / f"run-{stamp}"), "output bag directory "
              "(must not exist yet)", read_only=True),
            P("topics", list(DEFAULT_TOPICS), "topics to record", read_only=True),
            P("observers", [""], "observer names whose /obs/<name>/estimate is recorded",
              read_only=True),
            P("timestamps", "header", "bag time stamps: header (sample instant) or receive "
              "(wall clock)", choices=("header", "receive"), read_only=True),
            P("exit_on_done", True, "finalise and exit once the run is done and drained"),
            P("drain_timeout_s", 3.0, "after /drive/done: give up waiting for missing "
              "samples after this long without new messages", "s", 0.0, 600.0),
            P("scenario", "", "scenario of the run: its machine card and observer "
              "configurations go into the bag's metadata (for replay)", read_only=True),
            P("duration_s", 0.0, "run length for the metadata (0: the scenario's)", "s", 0.0,
              3600.0, read_only=True),
        ])
        self.pv = pv
        want = [t for t in pv["topics"] if t]
        want += [topics.estimate_topic(o) for o in pv["observers"] if o]
        self.want = list(dict.fromkeys(want))
        self.bag_dir = Path(pv["bag_dir"])
        if self.bag_dir.exists():
            raise ValueError(f"bag directory {self.bag_dir} exists already; choose a new one")
        try:
            self.bag_dir.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"cannot create {self.bag_dir.parent}: {exc}") from exc
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.store = typestore()
        self.writer = Writer(self.bag_dir, version=9, storage_plugin=StoragePlugin.MCAP)
        if pv["scenario"]:
            self._set_run_metadata(pv)
        self.writer.open()
        self.header_ts = pv["timestamps"] == "header"
        self.buf: list[tuple] = []
        self.lock = threading.Lock()
        self.conns: dict[str, object] = {}
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.last_seq: dict[str, int] = {}
        self.last_rx = time.monotonic()
        self.last_ts = 0
        self.done_seq: int | None = None
        self.closed = False
        self.pending = [t for t in self.want if not self._subscribe(t, conventional_type(t))]
        if self.pending:
            self._discover_timer = self.create_timer(0.2, self._discover)
        if pv["exit_on_done"]:
            self.create_subscription(UInt64, topics.DONE, self._on_done, qos.LATCHED)
            self._done_timer = self.create_timer(0.1, self._check_done)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._writer_loop, name="bag-writer", daemon=True)
        self.thread.start()
        self.get_logger().info(f"recording {len(self.want)} topics to {self.bag_dir}")

    def _set_run_metadata(self, pv) -> None:
        """The same custom_data fluxdrive.bagio.write_run_bag stores (machine card, observer
        configurations, scenario), so `./fluxdrive replay` treats graph bags like in-process
        ones.  Live parameter changes during the run are not reflected there."""
        import json
        from types import SimpleNamespace

        from fluxdrive.bagio import META_KEY, _json_default, run_metadata
        from fluxdrive.scenario import load_scenario, scenario_path

        sc = load_scenario(scenario_path(pv["scenario"]))
        if pv["duration_s"] > 0:
            sc.duration_s = pv["duration_s"]
        names = [o for o in pv["observers"] if o and o in sc.observers]
        meta = run_metadata(SimpleNamespace(scenario=sc, names=names, driving=sc.driving),
                            0, None, names)
        meta["recorded_by"] = "graph"
        self.writer.set_custom_data(META_KEY, json.dumps(meta, default=_json_default))

    # ----------------------------------------------------------------- subscriptions
    def _subscribe(self, topic: str, mtype: str | None) -> bool:
        if mtype is None:
            return False
        from fluxdrive_ros.topics import msg_class

        cls = msg_class(mtype)
        self.conns[topic] = self.writer.add_connection(topic, mtype, typestore=self.store)
        self.types[topic] = mtype
        self.counts[topic] = 0
        prof = {topics.DONE: qos.LATCHED, topics.CLOCK: qos.CLOCK}.get(topic, qos.SAMPLES_READER)
        conn = self.conns[topic]
        buf = self.buf
        if self.header_ts and mtype == topics.T_CLOCK:
            def cb(data: bytes, conn=conn, topic=topic):
                s, ns = _HDR.unpack_from(data, 4)
                t = s * 1_000_000_000 + ns
                self.last_ts = t
                buf.append((conn, t, data, topic, -1))
        elif self.header_ts and mtype.startswith("flux_drive_msgs/"):
            # Header first: stamp at bytes 4..12; seq right after the frame_id string
            has_seq = _seq_offset(mtype)

            def cb(data: bytes, conn=conn, topic=topic, has_seq=has_seq):
                s, ns = _HDR.unpack_from(data, 4)
                t = s * 1_000_000_000 + ns
                self.last_ts = t
                seq = -1
                if has_seq:
                    n = _U32.unpack_from(data, 12)[0]
                    off = 16 + n
                    off += (-(off - 4)) % 8
                    seq = _U64.unpack_from(data, off)[0]
                buf.append((conn, t, data, topic, seq))
        else:
            has_seq = _seq_offset(mtype)

            def cb(data: bytes, conn=conn, topic=topic, has_seq=has_seq):
                seq = -1
                if has_seq:
                    n = _U32.unpack_from(data, 12)[0]
                    off = 16 + n
                    off += (-(off - 4)) % 8
                    seq = _U64.unpack_from(data, off)[0]
                t = time.time_ns() if not self.header_ts else self.last_ts
                buf.append((conn, t, data, topic, seq))
        self.create_subscription(cls, topic, cb, prof, raw=True)
        return True

    def _discover(self) -> None:
        names = dict(self.get_topic_names_and_types())
        still = []
        for t in self.pending:
            ts = names.get(t)
            if ts:
                self._subscribe(t, ts[0])
                self.get_logger().info(f"recording {t} ({ts[0]})")
            else:
                still.append(t)
        self.pending = still
        if not still:
            self._discover_timer.cancel()

    # ----------------------------------------------------------------- writing
    def _take(self) -> list[tuple]:
        # swap the buffer (the executor thread appends to self.buf via the closures)
        buf = self.buf
        if not buf:
            return []
        items = buf[:]
        del buf[:len(items)]
        return items

    def _write(self, items: list[tuple]) -> None:
        w = self.writer.write
        counts, last = self.counts, self.last_seq
        for conn, t, data, topic, seq in items:
            w(conn, t, data)
            counts[topic] += 1
            if seq >= 0:
                last[topic] = seq
        if items:
            self.last_rx = time.monotonic()

    def _writer_loop(self) -> None:
        while not self.stop.is_set():
            items = self._take()
            if items:
                with self.lock:
                    if not self.closed:
                        self._write(items)
            else:
                time.sleep(0.02)

    # ----------------------------------------------------------------- end of run
    def _on_done(self, msg: UInt64) -> None:
        self.done_seq = int(msg.data)

    def _check_done(self) -> None:
        if self.done_seq is None or self.finished:
            return
        seen = [t for t, mt in self.types.items() if _seq_offset(mt) and self.counts[t] > 0]
        complete = all(self.last_seq.get(t, -1) >= self.done_seq for t in seen) and not self.buf
        quiet = time.monotonic() - self.last_rx > self.pv["drain_timeout_s"] and not self.buf
        if complete or quiet:
            if not complete:
                short = {t: self.last_seq.get(t, -1) for t in seen
                         if self.last_seq.get(t, -1) < self.done_seq}
                self.get_logger().warning(f"finishing without the last samples of {short}")
            self.finished = True

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=30.0)
        with self.lock:
            if self.closed:
                return
            self._write(self._take())
            self.closed = True
            self.writer.close()
        total = sum(self.counts.values())
        detail = ", ".join(f"{t} {c}" for t, c in self.counts.items())
        self.get_logger().info(f"bag {self.bag_dir} finalised: {total} messages ({detail})")
        sys.stdout.write(f"@bag {self.bag_dir}\n")
        sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    return main_node("fluxdrive_bringup.recorder:RecorderNode", "recorder", argv)


if __name__ == "__main__":
    sys.exit(main())
