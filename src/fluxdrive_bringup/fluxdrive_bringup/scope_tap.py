"""scope_tap: the per-sample topics of a running graph -> display envelopes for the scope.

Why a node of its own, inside the graph's process: a reader of every 10 kHz topic in another
process costs the lockstep loop most of its speed (each message is then sent over DDS; the
split layout, with only the recorder outside, runs at a quarter of the composed one's
real-time factor).  Inside the graph's process the tap's subscriptions are served by the
intra-process bus (fluxdrive_ros.intra), and its callback only appends the CDR bytes to a
list; every `period_s` a timer turns each list into numpy arrays in one go (the codec's
numpy dtype, no per-message Python decoding) and reduces them to min/max envelopes per
bucket of `bucket_samples` samples -- so a one-sample spike still shows as the envelope's
edge -- and publishes them as JSON on /scope/envelope, a few kB 30 times a second.
While nothing subscribes to /scope/envelope the callbacks drop the bytes.

`./fluxdrive run/launch --scope` put the tap into the graph's (drive) process; `./fluxdrive
scope` attached to a graph without one starts a tap in its own process (then every sample
crosses DDS: it works, but costs the lockstep graph much more).

Envelope JSON (one object per period)::

    {"v": 1, "ts_s": 1e-4, "bucket": 20, "seq": newest frame seq, "wall": time.time(),
     "rates": {topic: messages/s}, "mode": controller mode, "fault": fault reason or "",
     "enable": duty enable, "observers": [names],
     "streams": {stream: {"k": [bucket index...], "f": {field: [[min...], [max...]]}}},
     "locus": {observer: [[x...], [y...]]}}

Streams: "state" (i_d, i_q, i_d_ref, i_q_ref [A], speed_ref, speed_fb [rpm], mode),
"truth" (theta [deg], speed [rpm], omega_e [rad/s]), "duty" (a, b, c [-]) and "est/<name>"
(theta [deg], err [deg] = wrapped estimate minus truth when truth exists, omega_e [rad/s],
flux_mag [mVs], valid).  Bucket k spans samples k*bucket ... (k+1)*bucket-1; a bucket cut
by a period boundary arrives in two parts (the page merges them).
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Callable

import numpy as np
from fluxdrive_ros.cdr import Decoder
from fluxdrive_ros.intra import RawSubscription
from fluxdrive_ros.params import P, declare, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from std_msgs.msg import String

from fluxdrive_ros import qos, topics

RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
DEG = 180.0 / math.pi
ENVELOPE_QOS = 10  # depth: a slow scope skips periods, the graph never waits for it
_EST_RE = re.compile(r"^/obs/([^/]+)/estimate$")


def decode_batch(dec: Decoder, msgs: list[bytes], paths: list[str]) -> np.ndarray:
    """Columns `paths` of a list of serialised messages as an (n, len(paths)) float array,
    decoded with numpy over the codec's fixed layout (one frombuffer per string layout)."""
    out = np.empty((len(msgs), len(paths)))
    if not msgs:
        return out
    lens = {len(m) for m in msgs}
    groups = [(np.arange(len(msgs)), msgs)] if len(lens) == 1 else [
        (np.array(ix), [msgs[i] for i in ix])
        for ix in ([i for i, m in enumerate(msgs) if len(m) == n] for n in sorted(lens))]
    for ix, part in groups:
        codec = dec.codec_for(part[0])
        arr = np.frombuffer(b"".join(part), dtype=codec.numpy_dtype())
        for j, p in enumerate(paths):
            out[ix, j] = arr[f"f{codec.index(p)}"]
    return out


def envelope(seq: np.ndarray, cols: np.ndarray, bucket: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bucket indices and per-bucket min, max of every column (NaNs ignored; an all-NaN
    bucket gives NaN).  seq need not be sorted."""
    if len(seq) == 0:
        return np.empty(0, np.int64), np.empty((0, cols.shape[1])), np.empty((0, cols.shape[1]))
    order = np.argsort(seq, kind="stable")
    seq, cols = seq[order], cols[order]
    k = seq // bucket
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    lo = np.where(np.isnan(cols), np.inf, cols)
    hi = np.where(np.isnan(cols), -np.inf, cols)
    mn = np.minimum.reduceat(lo, starts, axis=0)
    mx = np.maximum.reduceat(hi, starts, axis=0)
    mn[np.isinf(mn)] = np.nan
    mx[np.isinf(mx)] = np.nan
    return k[starts], mn, mx


def wrap_deg(x: np.ndarray) -> np.ndarray:
    return (x + 180.0) % 360.0 - 180.0


def _jsonable(a: np.ndarray, decimals: int) -> list:
    """A float array as a JSON list, rounded; NaN -> null."""
    r = np.round(a, decimals)
    out = r.tolist()
    if np.isnan(r).any():
        out = [None if v != v else v for v in out]
    return out


# stream -> (message type, [(field name, message path(s), transform, decimals)])
# a transform takes the decoded columns (dict path -> array) and returns the field
def _col(p: str, scale: float = 1.0) -> Callable[[dict], np.ndarray]:
    return lambda c: c[p] * scale


STATE_FIELDS = [
    ("i_d", _col("i_dq[0]"), 3), ("i_q", _col("i_dq[1]"), 3),
    ("i_d_ref", _col("i_dq_ref[0]"), 3), ("i_q_ref", _col("i_dq_ref[1]"), 3),
    ("speed_ref", _col("omega_ref_m", RPM_PER_RAD_S), 2),
    ("speed_fb", _col("omega_fb_m", RPM_PER_RAD_S), 2),
    ("mode", _col("mode"), 0),
]
STATE_PATHS = ["seq", "i_dq[0]", "i_dq[1]", "i_dq_ref[0]", "i_dq_ref[1]", "omega_ref_m",
               "omega_fb_m", "mode"]
DUTY_FIELDS = [("a", _col("duty[0]"), 4), ("b", _col("duty[1]"), 4), ("c", _col("duty[2]"), 4)]
DUTY_PATHS = ["seq", "duty[0]", "duty[1]", "duty[2]", "enable"]
TRUTH_PATHS = ["seq", "theta_e", "omega_m"]
EST_PATHS = ["seq", "theta_e", "omega_e", "flux_ab[0]", "flux_ab[1]", "valid"]


class ScopeTapNode(FluxNode):
    def __init__(self, name: str = "scope_tap", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        self.specs = [
            P("period_s", 1.0 / 30.0, "publish the envelopes this often (the page's data "
              "rate) (live)", "s", 0.01, 1.0),
            P("bucket_samples", 20, "samples per envelope bucket (min/max over each bucket; "
              "the page shows one bucket per pixel or so) (live)", "-", 1, 10000),
            P("locus_points", 60, "flux-locus points per observer and period (every n-th "
              "sample) (live)", "-", 1, 2000),
        ]
        pv = declare(self, self.specs)
        fixed = declare(self, [
            P("observers", [""], "observer names to watch; empty: every /obs/<name>/estimate "
              "topic the graph has (discovered)", read_only=True),
            P("pole_pairs", 0, "pole pairs of the machine (truth speed in electrical rad/s "
              "next to the estimates); 0: from `scenario`, else not shown", "-", 0, 64,
              read_only=True),
            P("scenario", "", "scenario YAML (for pole_pairs and the sample period)",
              read_only=True),
            P("ts_s", 1e-4, "sample period (overridden by the scenario's)", "s", 1e-7, 1.0,
              read_only=True),
            P("exit_on_done", True, "end with the run (/drive/done), like the drive nodes, so "
              "that a process it shares with them can exit", read_only=True),
        ])
        self.pv = pv
        self.ts_s = fixed["ts_s"]
        self.pole_pairs = fixed["pole_pairs"]
        if fixed["scenario"]:
            from fluxdrive.core.scenario import load_scenario, scenario_path

            card = load_scenario(scenario_path(fixed["scenario"])).machine
            self.ts_s = card.ts_s
            self.pole_pairs = self.pole_pairs or card.pole_pairs
        self.buf: dict[str, list[bytes]] = {}
        self.decoders: dict[str, Decoder] = {}
        self.subs: list[RawSubscription] = []
        self.est_names: list[str] = []
        self.active = False
        self.truth_seq = np.empty(0, np.int64)
        self.truth_th = np.empty(0)
        self.last_t = time.monotonic()
        self.pub = self.create_publisher(String, topics.SCOPE_ENVELOPE, ENVELOPE_QOS)
        for topic, mtype in ((topics.CONTROLLER_STATE, topics.T_STATE),
                             (topics.DUTY, topics.T_DUTY), (topics.TRUTH, topics.T_TRUTH)):
            self._subscribe(topic, mtype)
        self.fixed_observers = [o for o in fixed["observers"] if o]
        for o in self.fixed_observers:
            self._add_observer(o)
        if not self.fixed_observers:
            self._discover()
            self.create_timer(1.0, self._discover)
        if fixed["exit_on_done"]:
            from std_msgs.msg import UInt64

            self.create_subscription(UInt64, topics.DONE, self._on_done, qos.LATCHED)
        on_set(self, self.specs, self._apply)
        self.timer = self.create_timer(pv["period_s"], self._tick)
        self.get_logger().info(f"scope tap on {len(self.subs)} topics, envelopes every "
                               f"{pv['period_s'] * 1e3:.0f} ms on {topics.SCOPE_ENVELOPE}")

    def _apply(self, changes: dict) -> str:
        self.pv = {**self.pv, **changes}
        if "period_s" in changes:
            self.timer.cancel()
            self.timer = self.create_timer(self.pv["period_s"], self._tick)
        return "applied"

    # --------------------------------------------------------------- subscriptions
    def _subscribe(self, topic: str, mtype: str) -> None:
        from fluxdrive_ros.topics import msg_class

        lst: list[bytes] = []
        self.buf[topic] = lst
        self.decoders[topic] = Decoder(mtype)
        append = lst.append

        def cb(data: bytes) -> None:
            if self.active:  # nobody watching: drop (the callback is all a sample costs)
                append(data)

        self.subs.append(RawSubscription(self, msg_class(mtype), topic, cb, qos.reader()))

    def _add_observer(self, name: str) -> None:
        if name in self.est_names:
            return
        self.est_names.append(name)
        self._subscribe(topics.estimate_topic(name), topics.T_ESTIMATE)

    def _discover(self) -> None:
        for t, _types in self.get_topic_names_and_types():
            m = _EST_RE.match(t)
            if m:
                self._add_observer(m.group(1))

    # --------------------------------------------------------------- envelopes
    def _take(self, topic: str) -> list[bytes]:
        lst = self.buf[topic]
        n = len(lst)
        out = lst[:n]
        del lst[:n]
        return out

    def _tick(self) -> None:
        now = time.monotonic()
        dt = max(now - self.last_t, 1e-6)
        self.last_t = now
        was = self.active
        self.active = self.pub.get_subscription_count() > 0
        if not was:
            for lst in self.buf.values():
                lst.clear()
            return
        msgs = {t: self._take(t) for t in self.buf}
        doc = self.envelopes(msgs, dt)
        self.pub.publish(String(data=json.dumps(doc, separators=(",", ":"))))

    def envelopes(self, msgs: dict[str, list[bytes]], dt: float) -> dict:
        """The envelope document of one period's messages (see the module doc)."""
        b = int(self.pv["bucket_samples"])
        streams: dict[str, dict] = {}
        doc: dict = {"v": 1, "ts_s": self.ts_s, "bucket": b, "wall": time.time(),
                     "rates": {t: round(len(m) / dt, 1) for t, m in msgs.items()},
                     "observers": list(self.est_names), "streams": streams, "locus": {}}
        seq_max = -1

        def put(stream: str, seq: np.ndarray, fields: list[tuple[str, np.ndarray, int]]) -> None:
            if len(seq) == 0:
                return
            cols = np.stack([f[1] for f in fields], axis=1)
            k, mn, mx = envelope(seq.astype(np.int64), cols, b)
            streams[stream] = {"k": k.tolist(), "f": {
                name: [_jsonable(mn[:, j], d), _jsonable(mx[:, j], d)]
                for j, (name, _, d) in enumerate(fields)}}

        # controller state (+ the drive's mode and latched fault)
        st = msgs.get(topics.CONTROLLER_STATE, [])
        if st:
            a = decode_batch(self.decoders[topics.CONTROLLER_STATE], st, STATE_PATHS)
            c = dict(zip(STATE_PATHS, a.T, strict=True))
            put("state", c["seq"], [(n, f(c), d) for n, f, d in STATE_FIELDS])
            doc["mode"] = int(c["mode"][-1])
            doc["fault"] = ""
            if doc["mode"] == 4:  # MODE_FAULT: the reason string of the newest message
                from fluxdrive_ros.cdr import read_strings

                doc["fault"] = read_strings(topics.T_STATE, st[-1]).get("fault_reason", "")
            seq_max = max(seq_max, int(c["seq"].max()))
        du = msgs.get(topics.DUTY, [])
        if du:
            a = decode_batch(self.decoders[topics.DUTY], du, DUTY_PATHS)
            c = dict(zip(DUTY_PATHS, a.T, strict=True))
            put("duty", c["seq"], [(n, f(c), d) for n, f, d in DUTY_FIELDS])
            doc["enable"] = bool(c["enable"][-1])
        tr = msgs.get(topics.TRUTH, [])
        if tr:
            a = decode_batch(self.decoders[topics.TRUTH], tr, TRUTH_PATHS)
            s = a[:, 0].astype(np.int64)
            th = a[:, 1]
            fields = [("theta", wrap_deg(th * DEG), 2), ("speed", a[:, 2] * RPM_PER_RAD_S, 2)]
            if self.pole_pairs:
                fields.append(("omega_e", a[:, 2] * self.pole_pairs, 3))
            put("truth", s, fields)
            # keep the last two periods' truth for the estimates' error (they may lag)
            keep = max(0, len(self.truth_seq) - 4 * len(s))
            self.truth_seq = np.r_[self.truth_seq[keep:], s]
            self.truth_th = np.r_[self.truth_th[keep:], th]
            o = np.argsort(self.truth_seq, kind="stable")
            self.truth_seq, self.truth_th = self.truth_seq[o], self.truth_th[o]
            seq_max = max(seq_max, int(s.max()))
        step = int(self.pv["locus_points"])
        for name in self.est_names:
            em = msgs.get(topics.estimate_topic(name), [])
            if not em:
                continue
            a = decode_batch(self.decoders[topics.estimate_topic(name)], em, EST_PATHS)
            s = a[:, 0].astype(np.int64)
            err = np.full(len(s), np.nan)
            if len(self.truth_seq):
                ix = np.clip(np.searchsorted(self.truth_seq, s), 0, len(self.truth_seq) - 1)
                hit = self.truth_seq[ix] == s
                err[hit] = wrap_deg((a[hit, 1] - self.truth_th[ix[hit]]) * DEG)
            fx, fy = a[:, 3], a[:, 4]
            put(f"est/{name}", s, [("theta", wrap_deg(a[:, 1] * DEG), 2), ("err", err, 2),
                                   ("omega_e", a[:, 2], 3),
                                   ("flux_mag", np.hypot(fx, fy) * 1e3, 4),
                                   ("valid", a[:, 5], 0)])
            n = max(1, len(s) // step)
            doc["locus"][name] = [_jsonable(fx[::n] * 1e3, 4), _jsonable(fy[::n] * 1e3, 4)]
        doc["seq"] = seq_max
        return doc

    def _on_done(self, _msg) -> None:
        # one more period for the last samples, then done
        self.create_timer(2.0 * self.pv["period_s"], lambda: setattr(self, "finished", True))

    def close(self) -> None:
        self.active = False


def main(argv: list[str] | None = None) -> int:
    return main_node("fluxdrive_bringup.scope_tap:ScopeTapNode", "scope_tap", argv)


if __name__ == "__main__":
    import sys

    sys.exit(main())
