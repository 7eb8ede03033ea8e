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
     "streams": {stream: {"k": [bucket index...], "n": [field names],
                          "lo": [[min of each field] per bucket], "hi": [[max ...] ...]}},
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
import struct
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from fluxdrive_ros.cdr import Decoder
from fluxdrive_ros.intra import RawSubscription
from fluxdrive_ros.params import P, declare, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from std_msgs.msg import UInt8MultiArray

from fluxdrive_ros import qos, topics

RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
DEG = 180.0 / math.pi
ENVELOPE_QOS = 10  # depth: a slow scope skips periods, the graph never waits for it
_EST_RE = re.compile(r"^/obs/([^/]+)/estimate$")


def decode_batch(dec: Decoder, msgs: list[bytes], paths: list[str]) -> np.ndarray:
    """Columns `paths` of a list of serialised messages as an (n, len(paths)) float array,
    decoded with numpy over the codec's fixed layout: one join and one frombuffer while the
    layout holds (the strings of a publisher are constant; a controller's fault reason
    changes its length), else one per layout."""
    out = np.empty((len(msgs), len(paths)))
    if not msgs:
        return out
    buf = b"".join(msgs)
    n0 = len(msgs[0])
    if len(buf) == n0 * len(msgs) and len(msgs[-1]) == n0:
        groups: list[tuple[Any, bytes, bytes]] = [(slice(None), msgs[0], buf)]
    else:
        by_len: dict[int, list[int]] = {}
        for i, m in enumerate(msgs):
            by_len.setdefault(len(m), []).append(i)
        groups = [
            (np.array(ix), msgs[ix[0]], b"".join(msgs[i] for i in ix)) for ix in by_len.values()
        ]
    for ix, first, data in groups:
        # over DDS a message may carry trailing padding: the layout of its prefix, with
        # the message's own length as the record size
        codec = dec.layout_of(first)
        key = (id(codec), len(first), tuple(paths))
        hit = _LAYOUTS.get(key)
        if hit is None or hit[0] is not codec:
            hit = _LAYOUTS[key] = (
                codec,
                codec.numpy_dtype(itemsize=len(first)),
                [f"f{codec.index(p)}" for p in paths],
            )
        arr = np.frombuffer(data, dtype=hit[1])
        for j, name in enumerate(hit[2]):
            out[ix, j] = arr[name]
    return out


_LAYOUTS: dict[tuple, tuple] = {}  # (codec, paths) -> (codec, numpy dtype, field names)


def envelope(
    seq: np.ndarray, cols: np.ndarray, bucket: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bucket indices and per-bucket min, max of every column (NaNs ignored; an all-NaN
    bucket gives NaN).  seq need not be sorted."""
    if len(seq) == 0:
        return np.empty(0, np.int64), np.empty((0, cols.shape[1])), np.empty((0, cols.shape[1]))
    if len(seq) > 1 and (seq[1:] < seq[:-1]).any():
        order = np.argsort(seq, kind="stable")
        seq, cols = seq[order], cols[order]
    k = seq // bucket
    starts = np.flatnonzero(np.diff(k, prepend=k[0] - 1))
    return k[starts], np.fmin.reduceat(cols, starts, axis=0), np.fmax.reduceat(cols, starts, axis=0)


def wrap_deg(x: np.ndarray) -> np.ndarray:
    return (x + 180.0) % 360.0 - 180.0


# ----------------------------------------------------------------- the wire format
# /scope/envelope carries a std_msgs/UInt8MultiArray (published as raw CDR) whose data is:
# u32 n, n bytes of JSON (every scalar, and per stream its name, field names, decimals and
# bucket count, per locus its point count), zero padding to 8 bytes, then little-endian
# float64 arrays in the order the JSON lists them: per stream k[nb], lo[nb, nf], hi[nb, nf];
# per locus xy[2, np].  Binary because the graph's process pays for every Python call: the
# JSON for the page (rounded numbers) is made by the scope server, in its own process.
_U32 = struct.Struct("<I")
_CDR_HEAD = b"\x00\x01\x00\x00" + _U32.pack(0) + _U32.pack(0)  # encapsulation, no dims, offset 0


def pack_envelopes(doc: dict) -> bytes:
    head = {k: v for k, v in doc.items() if k not in ("streams", "locus")}
    arrays = []
    head["streams"] = []
    for name, st in doc["streams"].items():
        head["streams"].append({"name": name, "n": st["n"], "dec": st["dec"], "nb": len(st["k"])})
        arrays += [st["k"].astype("<f8"), st["lo"].astype("<f8"), st["hi"].astype("<f8")]
    head["locus"] = []
    for name, xy in doc["locus"].items():
        head["locus"].append({"name": name, "np": xy.shape[1]})
        arrays.append(xy.astype("<f8"))
    hj = json.dumps(head, separators=(",", ":")).encode()
    pad = b"\0" * ((-(4 + len(hj))) % 8)
    data = b"".join([_U32.pack(len(hj)), hj, pad, *(a.tobytes() for a in arrays)])
    return _CDR_HEAD + _U32.pack(len(data)) + data


def page_json(cdr: bytes) -> tuple[str, int, float]:
    """A /scope/envelope message (raw CDR) -> the page's JSON text (numbers rounded per
    field; NaN -> null), the newest seq and the sample period."""
    data = memoryview(cdr)[16:]
    (n,) = _U32.unpack_from(data, 0)
    head = json.loads(bytes(data[4 : 4 + n]))
    off = 4 + n + (-(4 + n)) % 8

    def take(count: int) -> np.ndarray:
        nonlocal off
        a = np.frombuffer(data, dtype="<f8", count=count, offset=off)
        off += 8 * count
        return a

    streams = {}
    for st in head.pop("streams"):
        nb, nf = st["nb"], len(st["n"])
        q = 10.0 ** np.array(st["dec"], dtype=float)
        k = take(nb)
        lo, hi = take(nb * nf).reshape(nb, nf), take(nb * nf).reshape(nb, nf)
        streams[st["name"]] = {
            "k": k.astype(np.int64).tolist(),
            "n": st["n"],
            "lo": (np.round(lo * q) / q).tolist(),
            "hi": (np.round(hi * q) / q).tolist(),
        }
    locus = {}
    for lc in head.pop("locus"):
        locus[lc["name"]] = (np.round(take(2 * lc["np"]).reshape(2, -1) * 1e4) / 1e4).tolist()
    head["streams"], head["locus"] = streams, locus
    text = json.dumps(head, separators=(",", ":")).replace("NaN", "null")  # JSON has no NaN
    return text, int(head.get("seq", -1)), float(head.get("ts_s", 1e-4))


# stream -> (message type, [(field name, message path(s), transform, decimals)])
# a transform takes the decoded columns (dict path -> array) and returns the field
def _col(p: str, scale: float = 1.0) -> Callable[[dict], np.ndarray]:
    return lambda c: c[p] * scale


STATE_FIELDS = [
    ("i_d", _col("i_dq[0]"), 3),
    ("i_q", _col("i_dq[1]"), 3),
    ("i_d_ref", _col("i_dq_ref[0]"), 3),
    ("i_q_ref", _col("i_dq_ref[1]"), 3),
    ("speed_ref", _col("omega_ref_m", RPM_PER_RAD_S), 2),
    ("speed_fb", _col("omega_fb_m", RPM_PER_RAD_S), 2),
]
STATE_PATHS = [
    "seq",
    "i_dq[0]",
    "i_dq[1]",
    "i_dq_ref[0]",
    "i_dq_ref[1]",
    "omega_ref_m",
    "omega_fb_m",
    "mode",
]
DUTY_FIELDS = [("a", _col("duty[0]"), 4), ("b", _col("duty[1]"), 4), ("c", _col("duty[2]"), 4)]
DUTY_PATHS = ["seq", "duty[0]", "duty[1]", "duty[2]", "enable"]
TRUTH_PATHS = ["seq", "theta_e", "omega_m"]
EST_PATHS = ["seq", "theta_e", "omega_e", "flux_ab[0]", "flux_ab[1]"]


class ScopeTapNode(FluxNode):
    def __init__(self, name: str = "scope_tap", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        self.specs = [
            P(
                "period_s",
                0.04,
                "publish the envelopes this often (the page's data rate) (live)",
                "s",
                0.01,
                1.0,
            ),
            P(
                "bucket_samples",
                20,
                "samples per envelope bucket (min/max over each bucket; "
                "the page shows one bucket per pixel or so) (live)",
                "-",
                1,
                10000,
            ),
            P(
                "locus_points",
                60,
                "flux-locus points per observer and period (every n-th sample) (live)",
                "-",
                1,
                2000,
            ),
            P(
                "max_cpu_share",
                0.04,
                "at most this share of its process's CPU time goes to "
                "the envelopes: a period is skipped (its samples go into the next) while the "
                "tap is over it, so a slow or loaded graph is not slowed further (live)",
                "-",
                0.001,
                1.0,
            ),
        ]
        pv = declare(self, self.specs)
        fixed = declare(
            self,
            [
                P(
                    "observers",
                    [""],
                    "observer names to watch; empty: every /obs/<name>/estimate "
                    "topic the graph has (discovered)",
                    read_only=True,
                ),
                P(
                    "pole_pairs",
                    0,
                    "pole pairs of the machine (truth speed in electrical rad/s "
                    "next to the estimates); 0: from `scenario`, else not shown",
                    "-",
                    0,
                    64,
                    read_only=True,
                ),
                P(
                    "scenario",
                    "",
                    "scenario YAML (for pole_pairs and the sample period)",
                    read_only=True,
                ),
                P(
                    "ts_s",
                    1e-4,
                    "sample period (overridden by the scenario's)",
                    "s",
                    1e-7,
                    1.0,
                    read_only=True,
                ),
                P(
                    "exit_on_done",
                    True,
                    "end with the run (/drive/done), like the drive nodes, so "
                    "that a process it shares with them can exit",
                    read_only=True,
                ),
            ],
        )
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
        self.cpu_tap = 0.0  # CPU seconds spent in _tick since the tap became active
        self.cpu_proc0 = 0.0  # process CPU time when it became active
        self.skipped = 0
        self.pub = self.create_publisher(UInt8MultiArray, topics.SCOPE_ENVELOPE, ENVELOPE_QOS)
        for topic, mtype in (
            (topics.CONTROLLER_STATE, topics.T_STATE),
            (topics.DUTY, topics.T_DUTY),
            (topics.TRUTH, topics.T_TRUTH),
        ):
            self._subscribe(topic, mtype)
        self.fixed_observers = [o for o in fixed["observers"] if o]
        for o in self.fixed_observers:
            self._add_observer(o)
        if not self.fixed_observers:
            self._discover()
            self.create_timer(1.0, self._discover)
        if fixed["exit_on_done"]:
            self.create_subscription(
                topics.msg_class(topics.T_DONE),
                topics.DONE,
                self.graph.typed(topics.DONE, self._on_done),
                qos.LATCHED,
            )
        on_set(self, self.specs, self._apply)
        self.timer = self.create_timer(pv["period_s"], self._tick)
        self.get_logger().info(
            f"scope tap on {len(self.subs)} topics, envelopes every "
            f"{pv['period_s'] * 1e3:.0f} ms on {topics.SCOPE_ENVELOPE}"
        )

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
        c0 = time.process_time()  # CPU time of the whole process (every thread)
        was = self.active
        self.active = self.pub.get_subscription_count() > 0
        if not was or not self.active:
            for lst in self.buf.values():
                lst.clear()
            self.cpu_tap, self.cpu_proc0 = 0.0, c0
            self.last_t = time.monotonic()
            return
        # CPU budget: skip this period while the tap has had more than its share
        if self.cpu_tap > self.pv["max_cpu_share"] * (c0 - self.cpu_proc0):
            self.skipped += 1
            return
        now = time.monotonic()
        dt = max(now - self.last_t, 1e-6)
        self.last_t = now
        msgs = {t: self._take(t) for t in self.buf}
        doc = self.envelopes(msgs, dt)
        doc["skipped"] = self.skipped
        self.pub.publish(pack_envelopes(doc))  # raw CDR of a UInt8MultiArray
        self.cpu_tap += time.process_time() - c0

    def envelopes(self, msgs: dict[str, list[bytes]], dt: float) -> dict:
        """The envelope document of one period's messages (see the module doc)."""
        b = int(self.pv["bucket_samples"])
        streams: dict[str, dict] = {}
        doc: dict = {
            "v": 1,
            "ts_s": self.ts_s,
            "bucket": b,
            "wall": time.time(),
            "rates": {t: round(len(m) / dt, 1) for t, m in msgs.items()},
            "observers": list(self.est_names),
            "streams": streams,
            "locus": {},
        }
        seq_max = -1

        def put(stream: str, seq: np.ndarray, fields: list[tuple[str, np.ndarray, int]]) -> None:
            if len(seq) == 0:
                return
            cols = np.stack([f[1] for f in fields], axis=1)
            k, mn, mx = envelope(seq.astype(np.int64), cols, b)
            q = [f[2] for f in fields]
            # rows = buckets, columns = the fields in "n" order
            streams[stream] = {"k": k, "n": [f[0] for f in fields], "dec": q, "lo": mn, "hi": mx}

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
            put(
                f"est/{name}",
                s,
                [
                    ("theta", wrap_deg(a[:, 1] * DEG), 2),
                    ("err", err, 2),
                    ("omega_e", a[:, 2], 3),
                    ("flux_mag", np.hypot(fx, fy) * 1e3, 4),
                ],
            )
            n = max(1, len(s) // step)
            doc["locus"][name] = np.stack([fx[::n], fy[::n]]) * 1e3
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
