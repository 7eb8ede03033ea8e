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

Besides: per period the parameter markers seen ("markers"), the trigger state ("armed",
"pending") and the newest capture bag ("capture"); about once a wall second, per observer,
the newest `spectrum_window_s` of samples for the order spectra ("arrays" "spec/<name>":
rotor angle, θ̃ [rad], λ̂α [V s], truth flag), which the scope server turns into orders;
and, for the streams named in `raw_streams` (set by the scope server when the page asks for
an FFT, an edge trigger or a raw export), every period's full-rate samples as decoded
("arrays" "raw/<stream>": seq and the fields named in "raw_fields").

Streams: "frame" (i_a, i_b, i_c [A], v_ab, v_bc, v_ca, vdc [V]),
"state" (i_d, i_q, i_d_ref, i_q_ref [A], speed_ref, speed_fb [rpm], mode),
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from fluxdrive.core.schema import param
from fluxdrive.drive.control import MODE_FAULT
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive_ros.cdr import Decoder
from fluxdrive_ros.intra import RawSubscription
from fluxdrive_ros.params import P, config_params, declare, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from std_msgs.msg import UInt8MultiArray

from fluxdrive_ros import qos, topics

RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
DEG = 180.0 / math.pi
ENVELOPE_QOS = 10  # depth: a slow scope skips periods, the graph never waits for it


def decode_batch(dec: Decoder, msgs: list[bytes], paths: list[str]) -> dict[str, np.ndarray]:
    """Fields `paths` of a list of serialised messages, by their message path (`seq`,
    `i_abc[0]`, ...): float arrays decoded with numpy over the codec's fixed layout, one join
    and one frombuffer while the layout holds (the strings of a publisher are constant; a
    controller's fault reason changes its length), else one per layout."""
    out = np.empty((len(paths), len(msgs)))
    if not msgs:
        return dict(zip(paths, out, strict=True))
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
            out[j, ix] = arr[name]
    return dict(zip(paths, out, strict=True))


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
_STAMP = struct.Struct("<iI")  # header stamp (sec, nanosec) after the 4-byte CDR head
_CDR_HEAD = b"\x00\x01\x00\x00" + _U32.pack(0) + _U32.pack(0)  # encapsulation, no dims, offset 0


def pack_envelopes(doc: dict) -> bytes:
    head = {k: v for k, v in doc.items() if k not in ("streams", "locus", "arrays")}
    arrays = []
    head["streams"] = []
    for name, st in doc["streams"].items():
        head["streams"].append({"name": name, "n": st["n"], "dec": st["dec"], "nb": len(st["k"])})
        arrays += [st["k"].astype("<f8"), st["lo"].astype("<f8"), st["hi"].astype("<f8")]
    head["locus"] = []
    for name, xy in doc["locus"].items():
        head["locus"].append({"name": name, "np": xy.shape[1]})
        arrays.append(xy.astype("<f8"))
    head["arrays"] = []
    for name, a in doc.get("arrays", {}).items():
        head["arrays"].append({"name": name, "shape": list(a.shape)})
        arrays.append(np.ascontiguousarray(a, dtype="<f8"))
    hj = json.dumps(head, separators=(",", ":")).encode()
    pad = b"\0" * ((-(4 + len(hj))) % 8)
    data = b"".join([_U32.pack(len(hj)), hj, pad, *(a.tobytes() for a in arrays)])
    return _CDR_HEAD + _U32.pack(len(data)) + data


def unpack_envelopes(cdr: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """A /scope/envelope message (raw CDR) -> its head (streams and loci as arrays) and the
    extra arrays (the order-spectrum samples)."""
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
        k = take(nb)
        lo, hi = take(nb * nf).reshape(nb, nf), take(nb * nf).reshape(nb, nf)
        streams[st["name"]] = {"k": k, "n": st["n"], "dec": st["dec"], "lo": lo, "hi": hi}
    locus = {}
    for lc in head.pop("locus"):
        locus[lc["name"]] = take(2 * lc["np"]).reshape(2, -1)
    arrays = {}
    for ar in head.pop("arrays", []):
        shape = tuple(ar["shape"])
        arrays[ar["name"]] = take(int(np.prod(shape))).reshape(shape)
    head["streams"], head["locus"] = streams, locus
    return head, arrays


def page_json(cdr: bytes) -> tuple[str, dict]:
    """A /scope/envelope message (raw CDR) -> the page's JSON text (numbers rounded per
    field; NaN -> null) and its head (seq, ts_s, capture, ...).  The order spectra of the
    samples the tap sent along (`arrays` "spec/<observer>") are computed here, in the scope
    server's process, with the engine's harmonic code (order_spectrum)."""
    head, arrays = unpack_envelopes(cdr)
    streams = {}
    for name, st in head["streams"].items():
        q = 10.0 ** np.array(st["dec"], dtype=float)
        streams[name] = {
            "k": st["k"].astype(np.int64).tolist(),
            "n": st["n"],
            "lo": (np.round(st["lo"] * q) / q).tolist(),
            "hi": (np.round(st["hi"] * q) / q).tolist(),
        }
    head["streams"] = streams
    head["locus"] = {n: (np.round(xy * 1e4) / 1e4).tolist() for n, xy in head["locus"].items()}
    spectra = {}
    for name, a in arrays.items():
        if name.startswith("spec/"):
            spectra[name[5:]] = order_spectrum(*a)  # its rows: order_spectrum's arguments
    if spectra:
        head["spectrum"] = spectra
    text = json.dumps(head, separators=(",", ":")).replace("NaN", "null")  # JSON has no NaN
    head["raw"] = {n[4:]: a for n, a in arrays.items() if n.startswith("raw/")}  # server only
    return text, head


SPECTRUM_ORDERS = range(1, 21)


def order_spectrum(
    theta_rad: np.ndarray, err_rad: np.ndarray, flux_alpha_vs: np.ndarray, truth: np.ndarray
) -> dict[str, Any]:
    """Orders 1..20 against the rotor's electrical angle (the true one where `truth` is 1,
    else the observer's own) of the angle error θ̃ [deg] and of λ̂α [mV·s], over the
    largest whole number of electrical periods in the samples: the engine's definitions
    (fluxdrive.analysis.metrics.harmonic_spectrum, whole_periods), so the page shows the
    numbers `./fluxdrive run` reports."""
    from fluxdrive.analysis.metrics import harmonic_spectrum, whole_periods

    ok = np.isfinite(theta_rad) & np.isfinite(flux_alpha_vs)
    th, fa, e = theta_rad[ok], flux_alpha_vs[ok], err_rad[ok]
    out: dict[str, Any] = {"orders": list(SPECTRUM_ORDERS), "samples": int(len(th))}
    if len(th) < 16:
        return out
    unwrapped = np.unwrap(th)
    sl = whole_periods(unwrapped)
    thw = unwrapped[sl]
    out["periods"] = round(abs(float(thw[-1] - thw[0])) / (2 * math.pi), 2)
    out["flux_alpha"] = [
        round(v * 1e3, 5) for v in harmonic_spectrum(fa[sl], thw, SPECTRUM_ORDERS).values()
    ]
    if truth.size and bool(np.all(truth[ok] > 0.5)) and np.isfinite(e).all():
        out["err"] = [
            round(math.degrees(v), 5)
            for v in harmonic_spectrum(e[sl], thw, SPECTRUM_ORDERS).values()
        ]
    return out


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
    ("mode", _col("mode"), 0),
]
FRAME_FIELDS = [
    ("i_a", _col("i_abc[0]"), 3),
    ("i_b", _col("i_abc[1]"), 3),
    ("i_c", _col("i_abc[2]"), 3),
    ("v_ab", _col("v_ll[0]"), 2),
    ("v_bc", _col("v_ll[1]"), 2),
    ("v_ca", _col("v_ll[2]"), 2),
    ("vdc", _col("vdc"), 2),
]
FRAME_PATHS = ["seq", "i_abc[0]", "i_abc[1]", "i_abc[2]", "v_ll[0]", "v_ll[1]", "v_ll[2]", "vdc"]
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
TRIGGERS = ("off", "param", "mode", "fault", "threshold")
# a trigger may be seen after its sample: a parameter marker comes over DDS (up to a few
# tap periods late on a loaded machine); the armed tap keeps this much more history
TRIGGER_LATE_S = 0.5
# truth samples kept for the estimates' error: 1.6 s at 10 kHz, more than a truth block
# (256 rows) or a shadow's block of estimates (500) can lag
TRUTH_KEPT = 16384


class _Envelopes:
    """One period's streams: per stream its bucket indices and per-bucket min/max of each
    field (`streams`, for the document) and the decoded fields (`cols`, for the triggers)."""

    def __init__(self, bucket: int):
        self.bucket = bucket
        self.streams: dict[str, dict] = {}
        self.cols: dict[str, tuple[np.ndarray, dict[str, np.ndarray]]] = {}

    def put(self, stream: str, seq: np.ndarray, fields: list[tuple[str, np.ndarray, int]]) -> None:
        """fields: (name, values, decimals shown)."""
        if len(seq) == 0:
            return
        self.cols[stream] = (seq, {f[0]: f[1] for f in fields})
        arr = np.stack([f[1] for f in fields], axis=1)
        k, mn, mx = envelope(seq.astype(np.int64), arr, self.bucket)
        q = [f[2] for f in fields]
        # rows = buckets, columns = the fields in "n" order
        self.streams[stream] = {"k": k, "n": [f[0] for f in fields], "dec": q, "lo": mn, "hi": mx}


@dataclass
class TapEnvelope:
    """The envelopes the page draws: rate, buckets, locus, CPU share, spectra."""

    period_s: float = param(
        0.04,
        unit="s",
        doc="publish the envelopes this often (the page's data rate)",
        range=(0.01, 1.0),
    )
    bucket_samples: int = param(
        20,
        unit="-",
        doc="samples per envelope bucket (min/max over each bucket; the page "
        "shows one bucket per pixel or so)",
        range=(1, 10000),
    )
    locus_points: int = param(
        60,
        unit="-",
        doc="flux-locus points per observer and period (every n-th sample)",
        range=(1, 2000),
    )
    max_cpu_share: float = param(
        0.04,
        unit="-",
        doc="at most this share of its process's CPU time goes to the envelopes: "
        "a period is skipped (its samples go into the next) while the tap is "
        "over it, so a slow or loaded graph is not slowed further",
        range=(0.001, 1.0),
    )
    spectrum_window_s: float = param(
        1.0,
        unit="s",
        doc="order spectra of θ̃ and λ̂α over this much of the newest samples, renewed as often",
        range=(0.1, 10.0),
    )
    raw_streams: str = param(
        "",
        unit="",
        doc="send these streams' full-rate samples along with every envelope, for the "
        "scope server's FFT, edge triggers and raw export (comma-separated: frame, "
        "state, duty, truth, est/<observer>; the scope sets it; empty: none)",
    )


@dataclass
class TapCapture:
    """Single-shot captures: the trigger, the window, where the bags go."""

    trigger: str = param(
        "off",
        unit="",
        doc="single-shot capture: arm on a parameter change (param), a mode "
        "change such as the I-f -> observer handover (mode), a latched fault "
        "(fault) or |trigger_field| >= trigger_level (threshold); every set "
        "re-arms",
        choices=TRIGGERS,
    )
    trigger_field: str = param(
        "state:i_q",
        unit="",
        doc="threshold trigger: stream:field of the envelopes, e.g. state:i_q, "
        "frame:i_a, est/flux_measured:err",
    )
    trigger_level: float = param(
        1.0,
        unit="-",
        doc="threshold trigger: level of |field|",
        range=(-1e9, 1e9),
    )
    capture_pre_s: float = param(
        0.05,
        unit="s",
        doc="capture: full-rate samples kept before the trigger",
        range=(0.0, 1.0),
    )
    capture_post_s: float = param(
        0.1,
        unit="s",
        doc="capture: full-rate samples after the trigger",
        range=(0.001, 2.0),
    )
    capture_dir: str = param(
        str(REPO_ROOT / "bags" / "captures"),
        unit="",
        doc="capture: directory of the capture bags (one per trigger)",
    )


def live_params() -> list[P]:
    """The tap's live parameters (set while it runs; see _apply)."""
    return config_params(TapEnvelope()) + config_params(TapCapture())


@dataclass
class TapFixed:
    """The tap's read-only parameters (fixed at start)."""

    observers: tuple[str, ...] = param(
        (),
        unit="",
        doc="observer names to watch; empty: every /obs/<name>/estimate topic the"
        " graph has (discovered)",
        live=False,
    )
    pole_pairs: int = param(
        0,
        unit="-",
        doc="pole pairs of the machine (truth speed in electrical rad/s next to "
        "the estimates); 0: from `scenario`, else not shown",
        range=(0, 64),
        live=False,
    )
    scenario: str = param(
        "",
        unit="",
        doc="scenario YAML (for pole_pairs and the sample period)",
        live=False,
    )
    ts_s: float = param(
        1e-4,
        unit="s",
        doc="sample period (overridden by the scenario's)",
        range=(1e-7, 1.0),
        live=False,
    )
    exit_on_done: bool = param(
        True,
        unit="",
        doc="end with the run (/drive/done), like the drive nodes, so that a "
        "process it shares with them can exit",
        live=False,
    )


def fixed_params() -> list[P]:
    """The tap's read-only parameters (fixed at start)."""
    return config_params(TapFixed())


class ScopeTapNode(FluxNode):
    def __init__(self, name: str = "scope_tap", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        self.specs = live_params()
        self.pv = declare(self, self.specs)
        fixed = declare(self, fixed_params())
        self._timing(fixed)
        self._init_state()
        # in the drive's namespace (/a/scope/envelope), as every topic of the drive
        self.envelope_topic = topics.drive_topic(self, topics.SCOPE_ENVELOPE)
        self.pub = self.create_publisher(UInt8MultiArray, self.envelope_topic, ENVELOPE_QOS)
        self._subscribe_all(fixed)
        on_set(self, self.specs, self._apply)
        self.timer = self.create_timer(self.pv["period_s"], self._tick)
        self.get_logger().info(
            f"scope tap on {len(self.subs)} topics, envelopes every "
            f"{self.pv['period_s'] * 1e3:.0f} ms on {self.envelope_topic}"
        )

    def _timing(self, fixed: dict) -> None:
        """Sample period and pole pairs: the scenario's when one is given."""
        self.ts_s = fixed["ts_s"]
        self.pole_pairs = fixed["pole_pairs"]
        if fixed["scenario"]:
            from fluxdrive.drive.scenario import load_scenario, scenario_path

            card = load_scenario(scenario_path(fixed["scenario"])).machine
            self.ts_s = card.ts_s
            self.pole_pairs = self.pole_pairs or card.pole_pairs

    def _init_state(self) -> None:
        # the drive this tap belongs to (`__ns:=/a`: /a/drive/frame ...); the tap's keys and
        # its capture bags use the canonical names, as the recorder's bags do
        self.ns = topics.drive_namespace(self).rstrip("/")
        self.est_re = re.compile(rf"^{re.escape(self.ns)}/obs/([^/]+)/estimate$")
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
        self.types: dict[str, str] = {}
        self.spec: dict[str, list[np.ndarray]] = {}  # observer -> [rows (4, n) per period]
        # estimates newer than the newest truth, held until their truth arrives (the truth
        # comes in blocks, after the driving observer's own estimates): observer -> rows
        self.spec_pending: dict[str, np.ndarray] = {}
        self.spec_t0 = time.monotonic()
        self.last_mode: int | None = None
        self.markers: list[bytes] = []  # ParameterMarker CDR of this period
        self.marker_log: list[dict] = []  # markers of this period for the page
        # capture: the raw messages of the last periods (topic -> bytes) and their seq range
        self.hist: list[tuple[int, dict[str, list[bytes]]]] = []
        self.armed = False
        self.pending: dict[str, Any] | None = None  # a triggered capture waiting for its end
        self.last_capture: dict[str, Any] | None = None
        self.candidates: list[tuple[int, str]] = []
        self.marker_raw: list[bytes] = []

    def _subscribe_all(self, fixed: dict) -> None:
        """The per-sample topics, the observers (named, else discovered), the run's end and
        the parameter markers."""
        for topic, mtype in (
            (topics.FRAME, topics.T_FRAME),
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
                topics.drive_topic(self, topics.DONE),
                self.graph.typed(topics.DONE, self._on_done),
                qos.LATCHED,
            )
        self.create_subscription(
            topics.msg_class(topics.T_MARKER),
            topics.drive_topic(self, topics.MARKER),
            self._on_marker,
            qos.MARKERS,
            raw=True,
        )

    def _apply(self, changes: dict) -> str:
        self.pv = {**self.pv, **changes}
        if "trigger" in changes:  # every set of the trigger arms it afresh (single shot)
            self.armed = self.pv["trigger"] != "off"
            self.pending = None
        if "period_s" in changes:
            self.timer.cancel()
            self.timer = self.create_timer(self.pv["period_s"], self._tick)
        return "applied"

    # --------------------------------------------------------------- subscriptions
    def _subscribe(self, topic: str, mtype: str) -> None:
        from fluxdrive_ros.topics import msg_class

        lst: list[bytes] = []
        self.buf[topic] = lst
        self.types[topic] = mtype
        self.decoders[topic] = Decoder(mtype)
        append = lst.append

        def cb(data: bytes) -> None:
            if self.active:  # nobody watching: drop (the callback is all a sample costs)
                append(data)

        self.subs.append(
            RawSubscription(
                self, msg_class(mtype), topics.drive_topic(self, topic), cb, qos.reader()
            )
        )

    def _add_observer(self, name: str) -> None:
        if name in self.est_names:
            return
        self.est_names.append(name)
        self._subscribe(topics.estimate_topic(name), topics.T_ESTIMATE)

    def _on_marker(self, data: bytes) -> None:
        if self.active:
            self.markers.append(bytes(data))

    def _discover(self) -> None:
        for t, _types in self.get_topic_names_and_types():
            m = self.est_re.match(t)
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
            self.markers.clear()
            self.hist.clear()
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
        msgs[topics.MARKER], self.markers = self.markers, []
        doc = self.envelopes(msgs, dt)
        doc["skipped"] = self.skipped
        self._capture(msgs, doc)
        self.pub.publish(pack_envelopes(doc))  # raw CDR of a UInt8MultiArray
        self.cpu_tap += time.process_time() - c0

    # --------------------------------------------------------------- trigger and capture
    def _capture(self, msgs: dict[str, list[bytes]], doc: dict) -> None:
        """Keep the raw messages of the last periods while a trigger is armed or pending;
        on the trigger write the full-rate window around it into a bag (the project's
        one bag writer) and announce it in the envelopes (`capture`)."""
        seq_now = int(doc.get("seq", -1))
        if self.armed or self.pending is not None:
            self.hist.append((seq_now, msgs))
            keep = int(
                round(
                    (self.pv["capture_pre_s"] + self.pv["capture_post_s"] + TRIGGER_LATE_S)
                    / self.ts_s
                )
            )
            while len(self.hist) > 2 and self.hist[1][0] < seq_now - keep:
                self.hist.pop(0)
        if self.armed and self.candidates:
            trig, why = min(self.candidates)
            pre = int(round(self.pv["capture_pre_s"] / self.ts_s))
            post = int(round(self.pv["capture_post_s"] / self.ts_s))
            self.pending = {"seq": trig, "seq0": trig - pre, "seq1": trig + post, "why": why}
            self.armed = False
            self.get_logger().info(f"scope trigger at sample {trig}: {why}")
        p = self.pending
        if p is not None:
            doc["pending"] = p
            if p.get("ready"):  # one period after the window's end: every topic has it
                self.pending = None
                try:
                    self.last_capture = self.write_capture(p)
                except (OSError, ValueError) as exc:
                    self.last_capture = {"error": f"capture not written: {exc}", **p}
                    self.get_logger().error(self.last_capture["error"])
                self.hist.clear()
            elif seq_now >= p["seq1"]:
                p["ready"] = True
        doc["armed"] = self.armed
        if self.last_capture is not None:
            doc["capture"] = self.last_capture

    def write_capture(self, p: dict[str, Any]) -> dict[str, Any]:
        from fluxdrive.io.bagio import BagWriter
        from fluxdrive.io.bagwriter import check_bag_target

        why = re.sub(r"[^A-Za-z0-9_.-]+", "_", p["why"])[:40]
        name = f"capture-{time.strftime('%Y%m%d-%H%M%S')}-{p['seq']}-{why}"
        path = Path(self.pv["capture_dir"]) / name
        check_bag_target(path)
        by_topic: dict[str, list[bytes]] = {}
        for _seq, period in self.hist:
            for t, lst in period.items():
                by_topic.setdefault(t, []).extend(lst)
        info = {k: p[k] for k in ("seq", "seq0", "seq1", "why")}
        counts: dict[str, int] = {}
        with BagWriter(path, {"scope_capture": info, "ts_s": self.ts_s}) as w:
            for t, lst in by_topic.items():
                if not lst:
                    continue
                mtype = topics.T_MARKER if t == topics.MARKER else self.types[t]
                dec = self.decoders.get(t) or Decoder(mtype)
                seq = decode_batch(dec, lst, ["seq"])["seq"]
                sel = np.flatnonzero((seq >= p["seq0"]) & (seq <= p["seq1"]))
                if t == topics.MARKER:
                    sel = np.arange(len(lst))  # every marker of the window's periods
                if not len(sel):
                    continue
                cid = w.add_connection(t, mtype)
                for i in sel[np.argsort(seq[sel], kind="stable")]:
                    sec, nsec = _STAMP.unpack_from(lst[i], 4)
                    w.write(cid, sec * 1_000_000_000 + nsec, lst[i])
                counts[t] = len(sel)
        self.get_logger().info(f"scope capture: {sum(counts.values())} messages in {path}")
        return {**info, "path": str(path), "messages": counts}

    def _triggers(self, cols: dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]) -> None:
        """The trigger candidates (sample, why) of one period's decoded columns."""
        self.candidates = []
        src = self.pv["trigger"]
        st = cols.get("state")
        if st is not None and len(st[0]):
            seq, f = st
            mode = f["mode"].astype(np.int64)
            prev = np.r_[self.last_mode if self.last_mode is not None else mode[0], mode[:-1]]
            for i in np.flatnonzero(mode != prev):
                a, b = int(prev[i]), int(mode[i])
                if src == "mode" or (src == "fault" and b == MODE_FAULT):
                    self.candidates.append((int(seq[i]), f"mode {a} to {b}"))
            self.last_mode = int(mode[-1])
        if src == "param":
            from rclpy.serialization import deserialize_message

            cls = topics.msg_class(topics.T_MARKER)
            for raw in self.marker_raw:
                m = deserialize_message(raw, cls)
                self.candidates.append((int(m.seq), f"{m.node} {m.name}={m.value}"))
        if src == "threshold":
            stream, _, field = str(self.pv["trigger_field"]).rpartition(":")
            got = cols.get(stream)
            if got is not None and field in got[1]:
                hit = np.flatnonzero(np.abs(got[1][field]) >= self.pv["trigger_level"])
                if len(hit):
                    j = hit[np.argmin(got[0][hit])]
                    self.candidates.append(
                        (int(got[0][j]), f"{stream}:{field} >= {self.pv['trigger_level']:g}")
                    )

    def envelopes(self, msgs: dict[str, list[bytes]], dt: float) -> dict:
        """The envelope document of one period's messages (see the module doc)."""
        env = _Envelopes(int(self.pv["bucket_samples"]))
        self.marker_raw = msgs.get(topics.MARKER, [])
        doc: dict = {
            "v": 1,
            "ts_s": self.ts_s,
            "bucket": env.bucket,
            "wall": time.time(),
            "rates": {t: round(len(m) / dt, 1) for t, m in msgs.items() if t != topics.MARKER},
            "observers": list(self.est_names),
            "streams": env.streams,
            "locus": {},
        }
        seq_max = self._state_envelope(msgs.get(topics.CONTROLLER_STATE, []), env, doc)
        fr = msgs.get(topics.FRAME, [])
        if fr:
            c = decode_batch(self.decoders[topics.FRAME], fr, FRAME_PATHS)
            env.put("frame", c["seq"], [(n, f(c), d) for n, f, d in FRAME_FIELDS])
            seq_max = max(seq_max, int(c["seq"].max()))  # a bench without a controller
        du = msgs.get(topics.DUTY, [])
        if du:
            c = decode_batch(self.decoders[topics.DUTY], du, DUTY_PATHS)
            env.put("duty", c["seq"], [(n, f(c), d) for n, f, d in DUTY_FIELDS])
            doc["enable"] = bool(c["enable"][-1])
        seq_max = max(seq_max, self._truth_envelope(msgs.get(topics.TRUTH, []), env))
        for name in self.est_names:
            em = msgs.get(topics.estimate_topic(name), [])
            if em:
                self._estimate_envelope(name, em, env, doc)
        doc["seq"] = seq_max
        self._spectrum_samples(doc)
        self._raw_samples(env, doc)
        if self.marker_raw:
            doc["markers"] = self._marker_list()
        self._triggers(env.cols)
        return doc

    def _state_envelope(self, st: list[bytes], env: _Envelopes, doc: dict) -> int:
        """Controller state, the drive's mode and latched fault; the newest seq (-1: none)."""
        if not st:
            return -1
        c = decode_batch(self.decoders[topics.CONTROLLER_STATE], st, STATE_PATHS)
        env.put("state", c["seq"], [(n, f(c), d) for n, f, d in STATE_FIELDS])
        doc["mode"] = int(c["mode"][-1])
        doc["fault"] = ""
        if doc["mode"] == MODE_FAULT:  # the reason string of the newest message
            from fluxdrive_ros.cdr import read_strings

            doc["fault"] = read_strings(topics.T_STATE, st[-1]).get("fault_reason", "")
        return int(c["seq"].max())

    def _truth_envelope(self, tr: list[bytes], env: _Envelopes) -> int:
        """The true angle and speed; kept a while for the estimates' error. The newest seq."""
        if not tr:
            return -1
        c = decode_batch(self.decoders[topics.TRUTH], tr, TRUTH_PATHS)
        s = c["seq"].astype(np.int64)
        th, omega_m = c["theta_e"], c["omega_m"]
        fields = [("theta", wrap_deg(th * DEG), 2), ("speed", omega_m * RPM_PER_RAD_S, 2)]
        if self.pole_pairs:
            fields.append(("omega_e", omega_m * self.pole_pairs, 3))
        env.put("truth", s, fields)
        # keep the truth a while for the estimates' error (they may lag, or lead it by a
        # block): the newest TRUTH_KEPT samples, whatever a period brought
        keep = max(0, len(self.truth_seq) + len(s) - TRUTH_KEPT)
        self.truth_seq = np.r_[self.truth_seq[keep:], s]
        self.truth_th = np.r_[self.truth_th[keep:], th]
        o = np.argsort(self.truth_seq, kind="stable")
        self.truth_seq, self.truth_th = self.truth_seq[o], self.truth_th[o]
        return int(s.max())

    def _estimate_envelope(self, name: str, em: list[bytes], env: _Envelopes, doc: dict) -> None:
        """One observer's estimate, its error against the truth kept, its flux locus, and
        its samples for the order spectra."""
        c = decode_batch(self.decoders[topics.estimate_topic(name)], em, EST_PATHS)
        s, th_est = c["seq"].astype(np.int64), c["theta_e"]
        err = np.full(len(s), np.nan)
        th_true = np.full(len(s), np.nan)
        if len(self.truth_seq):
            ix = np.clip(np.searchsorted(self.truth_seq, s), 0, len(self.truth_seq) - 1)
            hit = self.truth_seq[ix] == s
            th_true[hit] = self.truth_th[ix[hit]]
            err[hit] = wrap_deg((th_est[hit] - th_true[hit]) * DEG)
        fx, fy = c["flux_ab[0]"], c["flux_ab[1]"]
        o = np.argsort(s, kind="stable")
        self._spectrum_rows(name, np.stack([s[o].astype(float), th_est[o], fx[o]]))
        env.put(
            f"est/{name}",
            s,
            [
                ("theta", wrap_deg(th_est * DEG), 2),
                ("err", err, 2),
                ("omega_e", c["omega_e"], 3),
                ("flux_mag", np.hypot(fx, fy) * 1e3, 4),
            ],
        )
        n = max(1, len(s) // int(self.pv["locus_points"]))
        doc["locus"][name] = np.stack([fx[::n], fy[::n]]) * 1e3

    def _spectrum_rows(self, name: str, rows: np.ndarray) -> None:
        """Samples for the order spectra (computed by the scope server): the rotor angle (true
        where known, else the estimate's), θ̃ [rad], λ̂α, truth flag. `rows` are seq, the
        estimated angle and λ̂α; those newer than the newest truth wait for it (at most
        TRUTH_KEPT samples: a graph without truth does not hold them)."""
        held = self.spec_pending.pop(name, None)
        if held is not None:
            rows = np.concatenate([held, rows], axis=1)
        if len(self.truth_seq):
            wait = rows[0] > self.truth_seq[-1]
            if wait.any() and wait.sum() < TRUTH_KEPT:
                self.spec_pending[name] = rows[:, wait]
                rows = rows[:, ~wait]
        if not rows.shape[1]:
            return
        s, th_est = rows[0].astype(np.int64), rows[1]
        th_true = np.full(len(s), np.nan)
        if len(self.truth_seq):
            ix = np.clip(np.searchsorted(self.truth_seq, s), 0, len(self.truth_seq) - 1)
            hit = self.truth_seq[ix] == s
            th_true[hit] = self.truth_th[ix[hit]]
        known = np.isfinite(th_true)
        err = np.where(known, np.radians(wrap_deg((th_est - th_true) * DEG)), np.nan)
        angle = np.where(known, th_true, th_est)
        self.spec.setdefault(name, []).append(np.stack([angle, err, rows[2], known.astype(float)]))

    def _spectrum_samples(self, doc: dict) -> None:
        """The newest spectrum_window_s of samples (sim time), sent at most once a wall
        second (`arrays` "spec/<observer>")."""
        n_win = int(round(self.pv["spectrum_window_s"] / self.ts_s))
        for rows in self.spec.values():
            if len(rows) > 1 and sum(r.shape[1] for r in rows[1:]) >= n_win:
                del rows[0]
        now = time.monotonic()
        full = [n for n, r in self.spec.items() if sum(x.shape[1] for x in r) >= n_win]
        if full and now - self.spec_t0 >= 1.0:
            self.spec_t0 = now
            doc.setdefault("arrays", {}).update(
                {f"spec/{n}": np.concatenate(self.spec.pop(n), axis=1)[:, -n_win:] for n in full}
            )

    def _raw_samples(self, env: _Envelopes, doc: dict) -> None:
        """The full-rate samples of the streams in `raw_streams` (`arrays` "raw/<stream>":
        rows seq and the stream's fields, named in `raw_fields`), as decoded for the
        envelopes: no second decode."""
        wanted = {s.strip() for s in str(self.pv["raw_streams"]).split(",") if s.strip()}
        for stream in sorted(wanted & set(env.cols)):
            seq, fields = env.cols[stream]
            doc.setdefault("arrays", {})[f"raw/{stream}"] = np.stack(
                [np.asarray(seq, dtype=float), *fields.values()]
            )
            doc.setdefault("raw_fields", {})[stream] = list(fields)

    def _marker_list(self) -> list[dict]:
        """This period's parameter markers, for the page."""
        from rclpy.serialization import deserialize_message

        cls = topics.msg_class(topics.T_MARKER)
        out = []
        for raw in self.marker_raw:
            m = deserialize_message(raw, cls)
            out.append(
                {
                    "seq": int(m.seq),
                    "node": m.node,
                    "name": m.name,
                    "value": m.value,
                    "ok": bool(m.successful),
                }
            )
        return out

    def _on_done(self, _msg) -> None:
        # one more period for the last samples, then done
        self.create_timer(2.0 * self.pv["period_s"], lambda: setattr(self, "finished", True))

    def close(self) -> None:
        self.active = False


def main(argv: list[str] | None = None) -> int:
    return main_node("fluxdrive_bringup.view.scope_tap:ScopeTapNode", "scope_tap", argv)


if __name__ == "__main__":
    import sys

    sys.exit(main())
