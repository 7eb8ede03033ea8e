"""`./fluxdrive scope`: a live scope of a running graph in the browser.

    ./fluxdrive scope [--port 8765] [--host 127.0.0.1] [--domain-id N]

prints `scope: http://127.0.0.1:PORT/?token=...` -- open it (the token is drawn afresh per
launch; every page, API call and WebSocket must carry it).  `./fluxdrive run/demo/launch
--scope` start the same server with the graph (and the scope tap in the graph's process).

Parts (one process):
- a ROS thread (rclpy context of its own, node /fluxdrive_scope): subscribes to the display
  envelopes of the scope tap (/scope/envelope, fluxdrive_bringup.view.scope_tap: binary, so that
  the graph's process does not pay for JSON), turns each into the page's JSON and forwards
  it to every open page over a WebSocket; publishes a ParameterMarker on
  /drive/param_marker for every parameter set from the page that the node refused (an
  accepted change is marked by the node itself, at the sample it took effect:
  fluxdrive_ros.params), so the bag shows when the operator changed what; if no tap
  publishes within --attach-wait,
  it starts one in this process (every sample then crosses DDS: works, costs the graph
  more -- see docs/scope.md);
- a worker thread for the parameter services (the same helpers as `./fluxdrive param`):
  list of nodes, each node's parameters with their declared descriptors, set (the node's
  refusal reason goes back to the page), and the fault reset (as node /fluxdrive_operator,
  the same rules as `./fluxdrive fault reset`);
- an aiohttp server: the page (scope_web/, uPlot vendored under scope_web/vendor), /ws, /api.

Binds 127.0.0.1 unless --host says otherwise (then anyone who can reach the port and has
the URL can set parameters and reset faults).  Every request passes the operator's rules
(fluxdrive_bringup.view.gate: a Host of this machine, no foreign page's Origin, the token for
everything but the page's scripts and styles, at most --max-clients live pages); a refusal
is one line to the client and one in the log, never a 500.  Started by the launcher, the URL
with its token goes to the launcher's console only, never into the log file.  Exit with
Ctrl-C; with --exit-on-done (run and demo use it) a second after the graph's /drive/done.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import os
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from fluxdrive.core.machine import ConfigError
from fluxdrive.core.paths import ROOT as REPO_ROOT
from fluxdrive.core.schema import Parser, option
from fluxdrive.io.graphfile import GraphSettings, ServeOptions
from fluxdrive_ros.topics import check_service_name

from fluxdrive_bringup.view.gate import Access, access_from_args, add_access_options

WEB_DIR = Path(__file__).resolve().parent / "scope_web"
SCOPE_NODE = "fluxdrive_scope"
_OWN_NODES = {"/" + SCOPE_NODE, "/fluxdrive_scope_params", "/fluxdrive_operator"}
MODE_NAMES = {0: "disabled", 1: "align", 2: "I/f ramp", 3: "closed loop", 4: "FAULT"}


# ------------------------------------------------------------------------ ROS side
class RosSide:
    """The envelope subscription and marker publisher, spun in a thread of their own."""

    def __init__(
        self,
        domain_id: int,
        on_envelope,
        attach_wait_s: float,
        quiet: bool = False,
        on_head=None,
        namespace: str = "",
    ):
        import rclpy
        from fluxdrive_ros.topics import msg_class
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import UInt8MultiArray

        from fluxdrive_ros import graph, qos, topics

        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(args=None, context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node(SCOPE_NODE, context=self.ctx, start_parameter_services=False)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.on_envelope = on_envelope
        self.last_seq = -1
        self.ts_s = 1e-4
        self.n_envelopes = 0
        self.done = threading.Event()
        self.local_tap: Any = None  # a ScopeTapNode when the graph has no tap of its own
        self.quiet = quiet
        # the drive's namespace ('' or /a): its envelopes, its end, its markers live there
        self.ns = namespace.rstrip("/")

        from fluxdrive_bringup.view.scope_tap import page_json

        def on_env(data: bytes) -> None:
            self.n_envelopes += 1
            try:
                text, head = page_json(data)
                seq, ts_s = int(head.get("seq", -1)), float(head.get("ts_s", 1e-4))
            except (ValueError, KeyError, struct.error) as exc:
                if self.n_envelopes < 5:
                    print(
                        f"scope: bad envelope message ({exc}); is the tap another version?",
                        flush=True,
                    )
                return
            self.note_envelope(seq, ts_s)
            on_envelope(text)
            if on_head is not None:
                on_head(head)

        self.sub = self.node.create_subscription(
            UInt8MultiArray, self.ns + topics.SCOPE_ENVELOPE, on_env, 10, raw=True
        )
        # the graph's id when started by its launch (else 0: any graph's end, and markers
        # stamped 0, which every recorder accepts; fluxdrive_ros.graph)
        self.graph_id = graph.env_id()

        def on_done(m) -> None:
            if self.graph_id in (0, m.graph_id):
                self.done.set()

        self.node.create_subscription(
            msg_class(topics.T_DONE), self.ns + topics.DONE, on_done, qos.LATCHED
        )
        self.marker_cls = msg_class(topics.T_MARKER)
        # reliable, transient-local: a recorder that matches late still gets the markers
        self.pub_marker = self.node.create_publisher(
            self.marker_cls, self.ns + topics.MARKER, qos.MARKERS
        )
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, name="scope-ros", daemon=True)
        self.thread.start()
        self.attach_wait_s = attach_wait_s
        threading.Thread(target=self._attach, name="scope-attach", daemon=True).start()

    def _spin(self) -> None:
        while not self.stop.is_set() and self.ctx.ok():
            try:
                self.ex.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - shutting down
                if self.stop.is_set() or not self.ctx.ok():
                    return
                raise

    def _attach(self) -> None:
        """No scope tap in the graph after the wait: run one here (direct subscriptions)."""
        t_end = time.monotonic() + self.attach_wait_s
        while time.monotonic() < t_end and not self.stop.is_set():
            if self.sub.get_publisher_count() > 0:
                return
            time.sleep(0.1)
        if self.stop.is_set() or self.sub.get_publisher_count() > 0:
            return
        from fluxdrive_bringup.view.scope_tap import ScopeTapNode

        print(
            "scope: no scope tap in the graph (start it with --scope to keep the cost low); "
            "tapping every sample topic from this process over DDS instead",
            flush=True,
        )
        self.local_tap = ScopeTapNode(
            "scope_tap_local", namespace=self.ns or None, context=self.ctx
        )
        self.ex.add_node(self.local_tap)

    def note_envelope(self, seq: int, ts_s: float) -> None:
        if seq >= 0:
            self.last_seq = seq
            self.ts_s = ts_s

    def publish_marker(self, node: str, name: str, value: str, ok: bool, reason: str) -> None:
        m = self.marker_cls()
        k = max(self.last_seq, 0)
        t_ns = int(round(k * self.ts_s * 1e9))
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        m.header.frame_id = ""
        m.seq = k
        m.graph_id = self.graph_id
        m.node, m.name, m.value = node, name, value
        m.successful, m.reason, m.source = ok, reason, "scope"
        self.pub_marker.publish(m)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2.0)
        try:
            if self.local_tap is not None:
                self.local_tap.destroy_node()
            self.node.destroy_node()
            self.ex.shutdown()
            self.ctx.try_shutdown()
        except Exception:  # noqa: BLE001 - shutting down anyway
            pass


class ParamSide:
    """Parameter services and the fault reset, on one worker thread (Session is not
    thread-safe; calls are serialised)."""

    def __init__(self, domain_id: int, wait_s: float = 3.0):
        self.domain_id = domain_id
        self.wait_s = wait_s
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="scope-params")
        self.session = None

    def _s(self):
        from fluxdrive_bringup.inspect.commands import Session

        if self.session is None:
            self.session = Session(
                domain_id=self.domain_id, wait_s=self.wait_s, node_name="fluxdrive_scope_params"
            )
            self.session.spin_for(0.5)
        return self.session

    def run(self, fn, *args):
        return asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)

    # the blocking calls (worker thread)
    def nodes(self) -> list[str]:
        s = self._s()
        s.spin_for(0.2)
        out = []
        # by name, not by node: a process's services are served by a hidden node of its own
        # (fluxdrive_ros.services)
        svcs = {n for n, _ in s.node.get_service_names_and_types()}
        for name, ns in s.node.get_node_names_and_namespaces():
            fqn = f"{ns.rstrip('/')}/{name}"
            if fqn in _OWN_NODES or name.startswith("fluxdrive_inspect_"):
                continue
            if f"{fqn}/describe_parameters" in svcs:
                out.append(fqn)
        return sorted(set(out))

    def describe(self, node: str) -> list[dict[str, Any]]:
        from fluxdrive_bringup.inspect.commands import _describe, _get, _list

        s = self._s()
        names = _list(s, node)
        descs = _describe(s, node, names)
        vals = _get(s, node, names)
        out = []
        for n, d, (typ, v) in zip(names, descs, vals, strict=True):
            lo = hi = None
            if d.floating_point_range:
                lo, hi = d.floating_point_range[0].from_value, d.floating_point_range[0].to_value
            elif d.integer_range:
                lo, hi = d.integer_range[0].from_value, d.integer_range[0].to_value
            choices = []
            if d.additional_constraints.startswith("one of:"):
                choices = [c.strip() for c in d.additional_constraints[7:].split(",")]
            out.append(
                {
                    "name": n,
                    "type": int(typ),
                    "value": _plain(v),
                    "description": d.description,
                    "read_only": bool(d.read_only),
                    "min": lo,
                    "max": hi,
                    "choices": choices,
                }
            )
        return out

    def set(self, node: str, name: str, text: str) -> tuple[bool, str, Any]:
        """Set; returns the node's answer and the value the node holds afterwards (the old
        one after a refusal), so the page shows what is in force."""
        from fluxdrive_bringup.inspect.commands import _get, set_param

        s = self._s()
        try:
            ok, reason, _ = set_param(s, node, name, text)
        finally:
            ((_, now),) = _get(s, node, [name])
        return ok, reason, _plain(now)

    def tap(self) -> str:
        """The scope tap's node name (the graph's, else the one this process started)."""
        taps = [n for n in self.nodes() if n.rsplit("/", 1)[-1].startswith("scope_tap")]
        if not taps:
            raise LookupError("no scope tap in the graph")
        return sorted(taps, key=len)[0]

    def reset(self, service: str) -> tuple[bool, str]:
        from fluxdrive_bringup.inspect.commands import OPERATOR_NODE, Session, reset_fault

        s = Session(domain_id=self.domain_id, wait_s=self.wait_s, node_name=OPERATOR_NODE)
        try:
            return reset_fault(s, service)
        finally:
            s.close()

    def close(self) -> None:
        def shut():
            if self.session is not None:
                self.session.close()

        try:
            self.pool.submit(shut).result(timeout=5)
        except Exception:  # noqa: BLE001
            pass
        self.pool.shutdown(wait=False)


CAPTURE_FIELDS = {  # capture chart series: (topic, message path, scale, label)
    "i_a": ("/drive/frame", "i_abc[0]", 1.0, "i_a [A]"),
    "i_b": ("/drive/frame", "i_abc[1]", 1.0, "i_b [A]"),
    "i_c": ("/drive/frame", "i_abc[2]", 1.0, "i_c [A]"),
    "vdc": ("/drive/frame", "vdc", 1.0, "v_dc [V]"),
    "i_d": ("/drive/controller_state", "i_dq[0]", 1.0, "i_d [A]"),
    "i_q": ("/drive/controller_state", "i_dq[1]", 1.0, "i_q [A]"),
    "mode": ("/drive/controller_state", "mode", 1.0, "mode"),
}


def load_capture(path: str | Path) -> dict[str, Any]:
    """A capture bag reopened with the project's bag reader: full-rate series on the sample
    time axis (phase currents, bus voltage, i_d/i_q, mode, θ̃ per observer), its markers
    and message counts -- the page's capture view."""
    import math

    import numpy as np
    from fluxdrive.io.bagio import columns, read_markers, read_raw

    from fluxdrive_ros import topics

    raws: dict[str, tuple[str, list[bytes]]] = {}
    for topic, mtype, _t, raw in read_raw(path):
        raws.setdefault(topic, (mtype, []))[1].append(bytes(raw))
    cols = {t: columns(mt, r) for t, (mt, r) in raws.items() if t != topics.MARKER}
    import yaml

    meta = (Path(path) / "metadata.yaml").read_text()
    custom = yaml.safe_load(meta)["rosbag2_bagfile_information"].get("custom_data") or {}
    settings = json.loads(custom.get("fluxdrive", "{}"))
    info = settings.get("scope_capture", {})
    ts_s = float(settings.get("ts_s", 1e-4))
    series: dict[str, dict[str, Any]] = {}

    def put(key: str, label: str, seq, vals) -> None:
        series[key] = {
            "label": label,
            "t": [round(float(k) * ts_s, 7) for k in seq],
            "v": [None if not math.isfinite(v) else round(float(v), 5) for v in vals],
        }

    for key, (topic, fpath, scale, label) in CAPTURE_FIELDS.items():
        c = cols.get(topic)
        if c is not None and fpath in c:
            put(key, label, c["seq"], c[fpath] * scale)
    tr = cols.get(topics.TRUTH)
    if tr is not None:
        order = np.argsort(tr["seq"])
        tseq, tth = tr["seq"][order], tr["theta_e"][order]
        for topic, c in cols.items():
            if not (topic.startswith("/obs/") and topic.endswith("/estimate")):
                continue
            ix = np.clip(np.searchsorted(tseq, c["seq"]), 0, len(tseq) - 1)
            hit = tseq[ix] == c["seq"]
            err = np.degrees((c["theta_e"][hit] - tth[ix[hit]] + np.pi) % (2 * np.pi) - np.pi)
            name = topic.split("/")[2]
            put(f"err/{name}", f"θ̃ {name} [deg]", c["seq"][hit], err)
    markers = read_markers(raws[topics.MARKER][1]) if topics.MARKER in raws else []
    return {
        "path": str(path),
        **info,
        "ts_s": ts_s,
        "series": series,
        "markers": markers,
        "messages": {t: len(r) for t, (_, r) in raws.items()},
    }


def _plain(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, float) and v != v:
        return None
    return v


# ------------------------------------------------------------------------ instrument
RAW_KEEP_S = 10.0  # sample seconds of full-rate samples kept per stream
RAW_WAIT_S = 20.0  # an export waits this long (wall) for the samples of its view
FFT_WAIT_S = 3.0  # an FFT waits this long for samples up to the end of its span
FFT_MIN_SAMPLES = 16
EDGE_EVENTS_KEPT = 20


def _num(v: float) -> float | None:
    return None if not math.isfinite(v) else float(f"{v:.7g}")


class Instrument:
    """The full-rate samples the tap sends along (`raw_streams`), kept per stream, and the
    edge trigger fed with them (the engine's fluxdrive.analysis.instrument: the maths is
    there, this only holds state between the ROS thread and the web handlers)."""

    def __init__(self) -> None:
        from fluxdrive.analysis.instrument import SampleBuffer

        self.lock = threading.Lock()
        self.buf = SampleBuffer(int(RAW_KEEP_S / 1e-4))
        self.ts_s = 1e-4
        self.wanted: set[str] = set()  # streams asked of the tap
        self.edge: Any = None  # an EdgeTrigger while one is set
        self.edge_cfg: dict[str, Any] = {}
        self.pending: list[Any] = []  # events waiting for their window's end
        self.events: list[dict[str, Any]] = []  # the newest, with their windows
        self.missing: dict[str, int] = {}  # stream -> samples that never arrived
        self.stopped = False  # the operator stopped the edge trigger
        self.last_raw: dict[str, float] = {}  # stream -> when its last samples came (wall)

    def on_head(self, head: dict) -> None:
        """ROS thread: an envelope's raw samples into the buffer and the edge trigger."""
        raw = head.get("raw") or {}
        if not raw:
            return
        names = head.get("raw_fields", {})
        with self.lock:
            self.ts_s = float(head.get("ts_s", self.ts_s))
            self.buf.max_samples = int(round(RAW_KEEP_S / self.ts_s))
            for stream, a in raw.items():
                flds = names.get(stream)
                if not flds or a.shape[0] != len(flds) + 1:
                    continue
                order = np.argsort(a[0], kind="stable")
                seq = a[0][order].astype(np.int64)
                fields = {f: a[1 + i][order] for i, f in enumerate(flds)}
                self._note_gaps(stream, seq)
                self.buf.put(stream, seq, fields)
                self.last_raw[stream] = time.monotonic()
                cfg = self.edge_cfg
                if self.edge is not None and cfg["stream"] == stream and cfg["field"] in fields:
                    self.pending += self.edge.feed(seq, fields[cfg["field"]])
            self._complete()

    def _note_gaps(self, stream: str, seq: np.ndarray) -> None:
        """Samples that never arrived (before the newest held, not in this block): said in
        the log and counted (an export or FFT of a span with a gap says so)."""
        last = self.buf.newest(stream)
        if last < 0 or not len(seq):
            return
        new = seq[seq > last]
        edges = np.r_[last, new]
        for i in np.flatnonzero(np.diff(edges) > 1)[:3]:
            a, b = int(edges[i]) + 1, int(edges[i + 1]) - 1
            self.missing[stream] = self.missing.get(stream, 0) + (b - a + 1)
            print(f"scope: {stream} samples {a}..{b} never arrived", flush=True)

    def _complete(self) -> None:
        """Events whose window (post_s after them) is held: with their samples, for the page."""
        cfg = self.edge_cfg
        if not self.pending or not cfg:
            return
        newest = self.buf.newest(cfg["stream"])
        post = int(round(cfg["post_s"] / self.ts_s))
        pre = int(round(cfg["pre_s"] / self.ts_s))
        while self.pending and self.pending[0].seq + post <= newest:
            ev = self.pending.pop(0)
            seq, v = self.buf.trace(cfg["trace"])
            sel = (seq >= ev.seq - pre) & (seq <= ev.seq + post)
            self.events.append(
                {
                    "n": len(self.events) + 1 if not self.events else self.events[-1]["n"] + 1,
                    "seq": ev.seq,
                    "t_s": round(ev.seq * self.ts_s, 9),
                    "auto": ev.auto,
                    "t": [round(float(k) * self.ts_s, 9) for k in seq[sel]],
                    "v": [_num(x) for x in v[sel].tolist()],
                }
            )
            del self.events[:-EDGE_EVENTS_KEPT]

    def set_edge(self, cfg: dict[str, Any]) -> None:
        from fluxdrive.analysis.instrument import EdgeTrigger

        with self.lock:
            ts = self.ts_s
            self.edge = EdgeTrigger(
                edge=cfg["edge"],
                level=cfg["level"],
                hysteresis=cfg["hysteresis"],
                mode=cfg["mode"],
                holdoff_samples=max(int(round((cfg["post_s"] + cfg["holdoff_s"]) / ts)), 1),
                auto_timeout_samples=max(int(round(cfg["auto_timeout_s"] / ts)), 1),
            )
            self.edge_cfg = cfg
            self.pending, self.events, self.stopped = [], [], False

    def stop_edge(self) -> None:
        """Disarm; the count and the events stay on show."""
        with self.lock:
            if self.edge is not None:
                self.edge.armed = False
            self.stopped, self.pending = True, []

    def edge_state(self) -> dict[str, Any]:
        with self.lock:
            e = self.edge
            return {
                "set": e is not None,
                "armed": bool(e is not None and e.armed),
                "stopped": self.stopped,
                "fired": int(e.fired) if e is not None else 0,
                "config": dict(self.edge_cfg),
                "events": list(self.events),
            }

    def held(self, stream: str) -> tuple[float, float] | None:
        """The sample times [s] of the oldest and newest sample held of `stream`."""
        with self.lock:
            a, b = self.buf.oldest(stream), self.buf.newest(stream)
            return None if b < 0 else (a * self.ts_s, b * self.ts_s)

    def covers(self, stream: str, t0_s: float, t1_s: float) -> bool:
        """Whether every sample of [t0, t1] is held (the view's first and last included)."""
        with self.lock:
            ts = self.ts_s
            a, b = self.buf.oldest(stream), self.buf.newest(stream)
            return b >= 0 and a <= math.ceil(t0_s / ts - 1e-6) and b >= math.floor(t1_s / ts + 1e-6)

    def view(self, stream: str, t0_s: float, t1_s: float):
        """Every sample of `stream` in [t0, t1]; LookupError naming how many never arrived
        when some did not (an export holds exactly the samples in view, or nothing)."""
        from fluxdrive.analysis.instrument import contiguous

        with self.lock:
            ts = self.ts_s
            seq, fields = self.buf.view(stream, ts, t0_s, t1_s)
        want = math.floor(t1_s / ts + 1e-6) - math.ceil(t0_s / ts - 1e-6) + 1
        if len(seq) != want or not contiguous(seq):
            raise LookupError(
                f"{want - len(seq)} of the view's {want} {stream} samples never reached the "
                "scope (see its log); export a span without them"
            )
        return seq, fields

    def spectrum(
        self, trace: str, window: str, t0_s: float, t1_s: float, ac: bool = False
    ) -> dict[str, Any]:
        """The amplitude spectrum of `trace` over the samples held in [t0, t1] (the newest
        gap-free run of them); `ac`: its mean removed first."""
        from fluxdrive.analysis.instrument import amplitude_spectrum, in_view

        with self.lock:
            seq, v = self.buf.trace(trace)
            ix = in_view(seq, self.ts_s, t0_s, t1_s)
            seq, v, ts = seq[ix], v[ix], self.ts_s
        gaps = np.flatnonzero(np.diff(seq) != 1)
        if len(gaps):
            seq, v = seq[gaps[-1] + 1 :], v[gaps[-1] + 1 :]
        if len(seq) < FFT_MIN_SAMPLES:
            raise LookupError(
                f"{trace}: {len(seq)} samples in the span so far (at least {FFT_MIN_SAMPLES})"
            )
        sp = amplitude_spectrum(v, ts, window, remove_mean=ac)
        return {
            "trace": trace,
            "window": window,
            "ac": ac,
            "n": sp.n,
            "t0_s": round(float(seq[0]) * ts, 9),
            "t1_s": round(float(seq[-1]) * ts, 9),
            "df_hz": sp.df_hz,
            "gap_cut": bool(len(gaps)),
            "scaling": "peak amplitude: a sine of amplitude A on a bin reads A",
            "f_hz": [round(f, 6) for f in sp.f_hz.tolist()],
            "amp": [_num(a) for a in sp.amplitude.tolist()],
        }


# ------------------------------------------------------------------------ web side
class Scope:
    def __init__(self, args):
        self.args = args
        self.access: Access = args.access
        self.token = self.access.token
        self.clients: set = set()
        self.sockets: set = set()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.latest: str | None = None
        self.sent = 0
        self.dropped = 0
        self.ros: RosSide | None = None
        self.params: ParamSide | None = None
        self.capture_path: str | None = None  # the newest capture bag the tap announced
        self.capture: dict[str, Any] | None = None  # ... reopened (load_capture)
        self.capture_pool = concurrent.futures.ThreadPoolExecutor(
            1, thread_name_prefix="scope-capture"
        )
        self.instrument = Instrument()

    # ROS thread: a capture the tap wrote is reopened from its bag (worker thread)
    def on_head(self, head: dict) -> None:
        self.instrument.on_head(head)
        cap = head.get("capture")
        if not cap or cap.get("path") in (None, self.capture_path):
            return
        self.capture_path = cap["path"]

        def load(path: str) -> None:
            try:
                self.capture = load_capture(path)
            except Exception as exc:  # noqa: BLE001 - a broken bag: say so on the page
                self.capture = {"path": path, "error": f"cannot reopen {path}: {exc}"}
            print(f"scope: capture {path} ({cap.get('why', '')})", flush=True)

        self.capture_pool.submit(load, cap["path"])

    # ROS thread -> event loop
    def on_envelope(self, text: str) -> None:
        if self.loop is not None:
            self.loop.call_soon_threadsafe(self._broadcast, text)

    def _broadcast(self, text: str) -> None:
        self.latest = text
        for q in list(self.clients):
            if q.full():  # a slow page skips periods instead of building a backlog
                q.get_nowait()
                self.dropped += 1
            q.put_nowait(text)

    def _authorised(self, request) -> bool:
        return self.access.has_token(request.path_qs, request.headers)

    def _refuse(self, request, status: int, reason: str, as_json: bool = False):
        """One line to the client (text, or JSON {error} for the API) and one to the log."""
        from aiohttp import web

        line = self.access.refused(str(request.remote), status, reason)
        if as_json:
            return web.json_response({"ok": False, "error": line.strip()}, status=status)
        return web.Response(status=status, text=line)

    def _no_token(self, request, as_json: bool = True):
        return self._refuse(
            request, 403, "missing or wrong token (use the URL the scope printed)", as_json
        )

    # handlers
    async def index(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request, as_json=False)
        return web.FileResponse(WEB_DIR / "index.html", headers={"Cache-Control": "no-store"})

    async def ws(self, request):
        from aiohttp import WSMsgType, web

        if not self._authorised(request):
            return self._no_token(request, as_json=False)
        if len(self.sockets) >= self.access.max_clients:
            return self._refuse(
                request,
                503,
                f"connection limit reached ({self.access.max_clients} pages; --max-clients)",
            )
        sock = web.WebSocketResponse(heartbeat=10.0, max_msg_size=1 << 20)
        await sock.prepare(request)
        q: asyncio.Queue = asyncio.Queue(maxsize=2)
        self.clients.add(q)
        self.sockets.add(sock)
        await sock.send_str(
            json.dumps({"hello": {"domain_id": self.args.domain_id, "modes": MODE_NAMES}})
        )
        if self.latest:
            q.put_nowait(self.latest)

        async def pump():
            while True:
                text = await q.get()
                await sock.send_str(text)
                self.sent += 1

        task = asyncio.create_task(pump())
        try:
            async for msg in sock:
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
        finally:
            task.cancel()
            self.clients.discard(q)
            self.sockets.discard(sock)
        return sock

    async def api_nodes(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        try:
            nodes = await self.params.run(self.params.nodes)
            out = []
            for n in nodes:
                for attempt in (1, 2):  # a node busy with a lockstep loop may answer late
                    try:
                        out.append(
                            {"node": n, "params": await self.params.run(self.params.describe, n)}
                        )
                        break
                    except (LookupError, TimeoutError) as exc:
                        if attempt == 2:
                            out.append({"node": n, "params": [], "error": str(exc)})
        except (LookupError, TimeoutError) as exc:
            return web.json_response({"error": str(exc)}, status=504)
        return web.json_response({"nodes": out})

    async def api_param(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        try:
            body = await request.json()
            node, name, text = str(body["node"]), str(body["name"]), str(body["value"])
        except (ValueError, KeyError, TypeError):
            return web.json_response(
                {"ok": False, "reason": "expected JSON {node, name, value}"}, status=400
            )
        try:
            ok, reason, value = await self.params.run(self.params.set, node, name, text)
        except (LookupError, TimeoutError) as exc:
            ok, reason, value = False, str(exc), None
        except Exception as exc:  # noqa: BLE001 - a value rclpy cannot even form
            ok, reason, value = False, f"{type(exc).__name__}: {exc}", None
        if not ok:  # an accepted change is marked by the node itself (exact sample)
            self.ros.publish_marker(node, name, text, ok, reason)
        print(
            f"scope: set {node} {name} = {text}: "
            f"{'ok' if ok else 'REFUSED'}{': ' + reason if reason else ''}",
            flush=True,
        )
        return web.json_response({"ok": ok, "reason": reason, "value": value})

    async def api_reset(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        # the drive's controller (in its namespace) unless the page names another service
        own = getattr(self.args, "namespace", "") + "/controller/reset_fault"
        service = request.query.get("service", own)
        try:
            check_service_name(service, "service")
        except ConfigError as exc:
            return self._refuse(request, 400, str(exc), as_json=True)
        try:
            ok, message = await self.params.run(self.params.reset, service)
        except (LookupError, TimeoutError) as exc:
            ok, message = False, str(exc)
        print(f"scope: fault reset {service}: {'ok' if ok else 'REFUSED'}: {message}", flush=True)
        return web.json_response({"ok": ok, "message": message})

    async def api_trigger(self, request):
        """Arm the tap's single-shot trigger: JSON {trigger, field?, level?, pre_s?, post_s?}
        set as the tap's parameters (the tap checks them like any parameter)."""
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        try:
            body = await request.json()
            sets = [("trigger", str(body["trigger"]))]
        except (ValueError, KeyError, TypeError):
            return web.json_response({"ok": False, "reason": "expected JSON {trigger}"}, 400)
        for key, name in (
            ("field", "trigger_field"),
            ("level", "trigger_level"),
            ("pre_s", "capture_pre_s"),
            ("post_s", "capture_post_s"),
        ):
            if key in body:
                sets.insert(0, (name, str(body[key])))  # the trigger itself last: it arms
        try:
            tap = await self.params.run(self.params.tap)
            for name, text in sets:
                ok, reason, _ = await self.params.run(self.params.set, tap, name, text)
                if not ok:
                    return web.json_response({"ok": False, "reason": f"{name}: {reason}"})
        except (LookupError, TimeoutError) as exc:
            return web.json_response({"ok": False, "reason": str(exc)})
        print(f"scope: trigger armed: {dict(sets)}", flush=True)
        return web.json_response({"ok": True, "reason": f"armed ({sets[-1][1]})"})

    async def api_capture(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        if self.capture is None:
            return web.json_response({"path": None})
        return web.json_response(self.capture)

    async def api_capture_mcap(self, request):
        """The newest capture's MCAP file (export)."""
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request, as_json=False)
        if self.capture is None or "error" in self.capture:
            return web.Response(status=404, text="no capture yet\n")
        files = sorted(Path(self.capture["path"]).glob("*.mcap"))
        if not files:
            return web.Response(status=404, text="capture has no MCAP file\n")
        return web.FileResponse(
            files[0],
            headers={
                "Content-Disposition": f'attachment; filename="{Path(self.capture["path"]).name}'
                '.mcap"',
                "Content-Type": "application/octet-stream",
            },
        )

    async def _want_raw(self, stream: str) -> str | None:
        """Ask the tap for `stream`'s full-rate samples (its `raw_streams`); None, or why not."""
        ins, params = self.instrument, self.params
        if stream in ins.wanted and time.monotonic() - ins.last_raw.get(stream, -1e9) < 5.0:
            return None  # asked, and its samples come (else ask again: a reset tap, a set)
        if params is None:
            return "the scope is not serving yet"
        text = ",".join(sorted(ins.wanted | {stream}))
        try:
            tap = await params.run(params.tap)
            ok, reason, _ = await params.run(params.set, tap, "raw_streams", text)
        except (LookupError, TimeoutError) as exc:
            return f"cannot ask the scope tap for {stream}'s samples: {exc}"
        if not ok:
            return f"the scope tap refused raw_streams={text}: {reason}"
        if stream not in ins.wanted:
            print(f"scope: full-rate samples of {text} asked of {tap}", flush=True)
        ins.wanted.add(stream)
        return None

    @staticmethod
    async def _until(pred, timeout_s: float) -> bool:
        """Wait (polling, 50 ms) until pred() holds or the timeout; whether it holds."""
        t_end = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() >= t_end:
                return False
            await asyncio.sleep(0.05)
        return True

    def _span(self, request) -> tuple[str, float, float]:
        """trace (stream:field), t0, t1 of a request; ValueError with the reason."""
        q = request.query
        trace = q.get("trace", "")
        if ":" not in trace:
            raise ValueError(f"trace {trace!r}: expected stream:field, e.g. frame:i_a")
        try:
            t0, t1 = float(q["t0"]), float(q["t1"])
        except (KeyError, ValueError):
            raise ValueError("expected t0 and t1 [s] (the view)") from None
        if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0):
            raise ValueError(f"the view {t0}..{t1} s is empty")
        return trace, t0, t1

    async def api_fft(self, request):
        """GET ?trace=stream:field&window=hann&t0=&t1=[&ac=1]: the amplitude spectrum in Hz
        of the trace's full-rate samples in the view (fluxdrive.analysis.instrument; ac=1:
        the mean removed first)."""
        from aiohttp import web
        from fluxdrive.analysis.instrument import WINDOWS

        if not self._authorised(request):
            return self._no_token(request)
        try:
            trace, t0, t1 = self._span(request)
        except ValueError as exc:
            return self._refuse(request, 400, str(exc), as_json=True)
        window = request.query.get("window", "hann")
        if window not in WINDOWS:
            why = f"window {window!r} is not one of {', '.join(WINDOWS)}"
            return self._refuse(request, 400, why, as_json=True)
        stream = trace.rpartition(":")[0]
        why = await self._want_raw(stream)
        if why:
            return web.json_response({"ok": False, "error": why}, status=503)
        ins = self.instrument
        await self._until(lambda: (ins.held(stream) or (0, -1))[1] >= t1 - ins.ts_s, FFT_WAIT_S)
        try:
            out = ins.spectrum(trace, window, t0, t1, request.query.get("ac", "0") == "1")
        except KeyError:
            why = f"no samples of {trace} yet (is it a trace the page shows?)"
            return web.json_response({"ok": False, "error": why}, status=404)
        except (LookupError, ValueError) as exc:
            return web.json_response({"ok": False, "error": str(exc)}, status=503)
        return web.json_response({"ok": True, **out})

    async def api_edge(self, request):
        """GET: the edge trigger's state and its newest events (with their samples);
        POST {trace, edge, level, hysteresis, mode, pre_s, post_s, holdoff_s,
        auto_timeout_s} sets and arms it, {"trace": ""} stops it."""
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        ins = self.instrument
        if request.method == "GET":
            return web.json_response(ins.edge_state())
        try:
            body = await request.json()
            trace = str(body["trace"])
            if not trace:
                ins.stop_edge()
                return web.json_response({"ok": True, "reason": "stopped"})
            cfg = {
                "trace": trace,
                "stream": trace.rpartition(":")[0],
                "field": trace.rpartition(":")[2],
                "edge": str(body.get("edge", "rising")),
                "mode": str(body.get("mode", "normal")),
            }
            for key, default in (
                ("level", 0.0),
                ("hysteresis", 0.0),
                ("pre_s", 0.005),
                ("post_s", 0.01),
                ("holdoff_s", 0.0),
                ("auto_timeout_s", 0.1),
            ):
                cfg[key] = float(body.get(key, default))
                if not math.isfinite(cfg[key]):
                    raise ValueError(f"{key} must be a finite number")
            if not cfg["stream"] or not 0 <= cfg["pre_s"] <= 1 or not 0 <= cfg["post_s"] <= 1:
                raise ValueError("expected trace stream:field, 0 <= pre_s, post_s <= 1 s")
            ins.set_edge(cfg)
        except (KeyError, TypeError, ValueError, ConfigError) as exc:
            why = f"edge trigger: {exc}" if str(exc) else "edge trigger: expected JSON {trace, ...}"
            return web.json_response({"ok": False, "reason": why}, status=400)
        why = await self._want_raw(cfg["stream"])
        if why:
            ins.stop_edge()
            return web.json_response({"ok": False, "reason": why}, status=503)
        print(f"scope: edge trigger armed: {cfg}", flush=True)
        return web.json_response({"ok": True, "reason": f"armed ({cfg['mode']})"})

    async def api_raw(self, request):
        """GET /api/raw.csv or /api/raw.mcap ?trace=stream:field&t0=&t1=: every full-rate
        sample of the trace's stream in the view, once they are all held (waits up to
        RAW_WAIT_S: the samples of a live view's end may still be on their way)."""
        from aiohttp import web
        from fluxdrive.io.scope_export import raw_csv, write_raw_bag

        if not self._authorised(request):
            return self._no_token(request)
        try:
            trace, t0, t1 = self._span(request)
        except ValueError as exc:
            return self._refuse(request, 400, str(exc), as_json=True)
        stream = trace.rpartition(":")[0]
        why = await self._want_raw(stream)
        if why:
            return web.json_response({"ok": False, "error": why}, status=503)
        ins = self.instrument
        if not await self._until(lambda: ins.covers(stream, t0, t1), RAW_WAIT_S):
            held = ins.held(stream)
            span = f"{held[0]:.4f}..{held[1]:.4f} s" if held else "nothing yet"
            why = (
                f"the view {t0:.4f}..{t1:.4f} s is not all held: {stream} samples held "
                f"{span} (they start when first asked for; zoom into that span)"
            )
            return self._refuse(request, 409, why, as_json=True)
        try:
            seq, fields = ins.view(stream, t0, t1)
        except LookupError as exc:
            return self._refuse(request, 409, str(exc), as_json=True)
        ts = ins.ts_s
        name = f"scope-{stream.replace('/', '_')}-{int(seq[0])}-{int(seq[-1])}"
        if request.path.endswith(".csv"):
            return web.Response(
                text=raw_csv({stream: (seq, fields)}, ts),
                content_type="text/csv",
                headers={"Content-Disposition": f'attachment; filename="{name}.csv"'},
            )
        from fluxdrive.io.bagwriter import check_bag_target

        path = Path(self.args.export_dir) / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"
        try:
            check_bag_target(path)
        except ValueError as exc:
            return self._refuse(request, 409, str(exc), as_json=True)
        info = {"t0_s": t0, "t1_s": t1, "seq0": int(seq[0]), "seq1": int(seq[-1])}
        loop = asyncio.get_running_loop()
        mcap = await loop.run_in_executor(
            self.capture_pool, write_raw_bag, path, {stream: (seq, fields)}, ts, info
        )
        print(f"scope: raw export of {stream} {t0}..{t1} s: {path}", flush=True)
        return web.FileResponse(
            mcap,
            headers={
                "Content-Disposition": f'attachment; filename="{name}.mcap"',
                "Content-Type": "application/octet-stream",
                "X-Fluxdrive-Bag": path.name,
            },
        )

    async def api_status(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return self._no_token(request)
        r = self.ros
        return web.json_response(
            {
                "envelopes": r.n_envelopes,
                "sent": self.sent,
                "dropped": self.dropped,
                "clients": len(self.clients),
                "local_tap": r.local_tap is not None,
                "last_seq": r.last_seq,
                # the full-rate samples held per stream: [first, last] sample time [s]
                "raw": {s: self.instrument.held(s) for s in sorted(self.instrument.wanted)},
                "raw_missing": dict(self.instrument.missing),
            }
        )

    @staticmethod
    def _page_guard(scope: Scope):
        """Middleware: every request's Host and Origin checked (gate.Access.where); the page
        itself (index.html) served only with the token, also under /static/ (the scripts and
        styles it loads carry no token and no secret); an unforeseen error in a handler is
        one line to the client and the log, not aiohttp's 500 page."""
        from aiohttp import web

        @web.middleware
        async def guard(request, handler):
            bad = scope.access.where(request.headers)
            if bad is not None:
                return scope._refuse(request, *bad, as_json=request.path.startswith("/api/"))
            if (
                request.path.startswith("/static/")
                and Path(request.path).name.lower() == "index.html"
                and not scope._authorised(request)
            ):
                return scope._refuse(request, 403, "the page needs its token")
            try:
                return await handler(request)
            except web.HTTPException:
                raise
            except Exception as exc:  # noqa: BLE001 - one line, never a traceback page
                why = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
                return scope._refuse(request, 400, f"cannot serve {request.path}: {why}", True)

        return guard

    def app(self):
        from aiohttp import web

        app = web.Application(middlewares=[self._page_guard(self)])
        app.router.add_get("/", self.index)
        app.router.add_get("/ws", self.ws)
        app.router.add_get("/api/nodes", self.api_nodes)
        app.router.add_post("/api/param", self.api_param)
        app.router.add_post("/api/reset", self.api_reset)
        app.router.add_get("/api/status", self.api_status)
        app.router.add_post("/api/trigger", self.api_trigger)
        app.router.add_get("/api/capture", self.api_capture)
        app.router.add_get("/api/capture.mcap", self.api_capture_mcap)
        app.router.add_get("/api/fft", self.api_fft)
        app.router.add_get("/api/edge", self.api_edge)
        app.router.add_post("/api/edge", self.api_edge)
        app.router.add_get("/api/raw.csv", self.api_raw)
        app.router.add_get("/api/raw.mcap", self.api_raw)
        app.router.add_static("/static/", WEB_DIR, show_index=False)
        return app

    async def serve(self) -> int:
        from aiohttp import web

        self.loop = asyncio.get_running_loop()
        dom = self.args.domain_id
        self.ros = RosSide(
            dom,
            self.on_envelope,
            self.args.attach_wait,
            on_head=self.on_head,
            namespace=getattr(self.args, "namespace", ""),
        )
        self.params = ParamSide(dom)
        quiet_bad_requests()
        runner = web.AppRunner(self.app(), access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, self.args.host, self.args.port)
        try:
            await site.start()
        except OSError as exc:
            print(
                f"scope: cannot listen on {self.args.host}:{self.args.port}: {exc.strerror or exc}",
                file=sys.stderr,
            )
            await runner.cleanup()
            self.ros.close()
            return 1
        port = runner.addresses[0][1]
        host = self.args.host if self.args.host not in ("0.0.0.0", "::") else "127.0.0.1"
        url = f"http://{host}:{port}/?token={self.token}"
        if os.environ.get("FLUXDRIVE_GRAPH_KEY"):  # started by the launcher (--scope)
            # the launcher's log file keeps this output: the address without its token
            print(f"scope: http://{host}:{port}/ (the URL with its token: on the console)")
            print(f"@scope-url {url}", flush=True)
        else:
            print(f"scope: {url}", flush=True)
        stop = asyncio.Event()
        import signal

        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self.loop.add_signal_handler(sig, stop.set)
            except (NotImplementedError, RuntimeError):
                pass
        try:
            while not stop.is_set():
                try:
                    await asyncio.wait_for(stop.wait(), 0.25)
                except TimeoutError:
                    pass
                if self.args.exit_on_done and self.ros.done.is_set():
                    await asyncio.sleep(1.0)  # the last envelopes reach the page
                    break
        finally:
            for sock in list(self.sockets):  # a clean close: the page says "disconnected"
                await sock.close(code=1001, message=b"scope stopped")
            await runner.cleanup()
            self.params.close()
            self.ros.close()
            self.capture_pool.shutdown(wait=False)
        return 0


class _OneLineBadRequest(logging.Filter):
    """aiohttp logs a request it cannot parse (an oversized header, garbage on the port) with
    a full traceback; a client's bad request is one line naming the client and the reason."""

    def filter(self, record: logging.LogRecord) -> bool:
        from aiohttp.http_exceptions import HttpProcessingError

        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, HttpProcessingError):
            remote = record.args[0] if isinstance(record.args, tuple) and record.args else "?"
            why = (exc.message or type(exc).__name__).splitlines()[0][:200]
            record.msg = "scope: refused a bad request from %s: %s %s"
            record.args = (remote, exc.code, why)
            record.exc_info = None
            record.exc_text = None
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True


def quiet_bad_requests() -> None:
    log = logging.getLogger("aiohttp.server")
    if not any(isinstance(f, _OneLineBadRequest) for f in log.filters):
        log.addFilter(_OneLineBadRequest())


def main(argv: list[str] | None = None) -> int:
    ap = Parser(prog="fluxdrive scope", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)"
    )
    option(ap, "--port", ServeOptions, help="TCP port (default 8765; 0: any free port)")
    add_access_options(ap)
    option(ap, "--domain-id", GraphSettings, help="ROS_DOMAIN_ID of the graph")
    ap.add_argument(
        "--attach-wait",
        type=float,
        default=3.0,
        help="seconds to wait for the graph's scope tap before tapping the "
        "topics directly (default 3)",
    )
    ap.add_argument(
        "--exit-on-done", action="store_true", help="exit a second after the graph's /drive/done"
    )
    ap.add_argument(
        "--export-dir",
        default=str(REPO_ROOT / "bags" / "exports"),
        help="where raw MCAP exports of the view go, one bag each (default bags/exports)",
    )
    ap.add_argument(
        "--namespace",
        default="",
        help="the drive's ROS namespace (e.g. /bench_a: its /bench_a/scope/envelope, markers "
        "on /bench_a/drive/param_marker; default: the root namespace)",
    )
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    from fluxdrive_ros.topics import check_namespace

    try:
        args.namespace = check_namespace(args.namespace, "--namespace")
        args.access = access_from_args(args, "scope")
    except ConfigError as exc:
        print(f"scope: {exc}", file=sys.stderr)
        return 2
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.domain_id is None:
        args.domain_id = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    try:
        import aiohttp  # noqa: F401
    except ImportError:
        print(
            "scope: aiohttp is not installed; run ./fluxdrive help (set-up) first", file=sys.stderr
        )
        return 2
    return asyncio.run(Scope(args).serve())


if __name__ == "__main__":
    sys.exit(main())
