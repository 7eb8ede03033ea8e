"""Run <-> rosbag2 (mcap) without ROS: the one writer and reader of drive bags.

Topics (the graph recorder uses the same names and types):

  /drive/frame             flux_drive_msgs/msg/PhaseFrame      one per PWM period (FR_* row)
  /drive/truth             flux_drive_msgs/msg/PlantTruth      simulation ground truth (TR_*)
  /drive/duty              flux_drive_msgs/msg/DutyCommand     the controller's output
  /drive/controller_state  flux_drive_msgs/msg/ControllerState the controller's state (CO_*)
  /obs/<name>/estimate     flux_drive_msgs/msg/RotorEstimate   one per frame per observer (ES_*)

Messages are matched by `seq` (the PWM period index), not by arrival order.  A bag written
here also carries, in metadata custom_data, the machine card, the observers' configurations
and (for a bag cut out of a longer run) the observers' states at the first frame, so a
replay of the same variant and parameters reproduces the recorded estimates exactly.

Only `rosbags` is used (no rclpy): tests and the sample bags need no ROS graph.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError, MachineCard
from fluxdrive.drive.control import CO_N
from fluxdrive.drive.observers import ES_N, KernelObserver, ObserverConfig
from fluxdrive.drive.plant import FR_N, FR_SEQ, TR_N, TR_T, TR_THETA_E
from fluxdrive.io import messages
from fluxdrive.io.cdr import Decoder, layout_type, read_strings
from fluxdrive.io.topics import (
    CONTROLLER_STATE,
    DUTY,
    ESTIMATE,
    FRAME,
    MARKER,
    MSG_SRC_DIR,
    OBS_NAMESPACE,
    SETTINGS,
    T_DUTY,
    T_ESTIMATE,
    T_FRAME,
    T_MARKER,
    T_STATE,
    T_STRING,
    T_TRUTH,
    TRUTH,
    offered_lifespan_s,
    offered_qos,
)

TOPIC_FRAME, TOPIC_TRUTH, TOPIC_DUTY, TOPIC_CTRL = FRAME, TRUTH, DUTY, CONTROLLER_STATE
EST_PREFIX, EST_SUFFIX = f"{OBS_NAMESPACE}/", f"/{ESTIMATE}"
T_CTRL, T_EST = T_STATE, T_ESTIMATE
MSG_DIR = MSG_SRC_DIR
META_KEY = "fluxdrive"  # custom_data key: JSON with machine, observers, scenario, states


class BagError(ConfigError):
    """A bag that cannot be replayed; the message names the problem in one line."""


def est_topic(name: str) -> str:
    return f"{EST_PREFIX}{name}{EST_SUFFIX}"


_STORE = None


def typestore():
    """rosbags typestore: ROS 2 Jazzy's standard types + every flux_drive_msgs message,
    registered from the .msg sources (so every bag embeds its definitions).  The one
    typestore of the project (the graph's recorder and bag reader use it too)."""
    global _STORE
    if _STORE is None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        store = get_typestore(Stores.ROS2_JAZZY)
        types = {}
        for p in sorted(MSG_DIR.glob("*.msg")):
            types.update(get_types_from_msg(p.read_text(), f"flux_drive_msgs/msg/{p.stem}"))
        store.register(types)
        _STORE = store
    return _STORE


# ------------------------------------------------------------------ writing
class _McapStorage:
    """rosbags' storage-writer interface over fluxdrive.io.mcapfile (MCAP written in bulk), so
    the project's bags open in every MCAP tool: zstd chunk compression (inside the MCAP, not a
    compressed file), messages sorted by log time within each chunk, a sequence number per
    channel, the offered QoS per channel, and extra MCAP metadata records (the recorder's
    settings) next to rosbag2's own."""

    def __init__(self, path: Path, compression: Any) -> None:
        from fluxdrive.io.mcapfile import McapFile

        _ = compression  # rosbags' file/message compression: never used (chunks are zstd)
        self.path = path / f"{path.name}.mcap"
        self.file = McapFile(self.path)
        self.schema_ids: dict[str, int] = {}
        self.channel_ids: dict[int, int] = {}  # rosbags connection id -> MCAP channel id
        self.records: dict[str, dict[str, str]] = {}
        self.ros_distro = ROS_DISTRO

    def add_msgtype(self, connection: Any) -> None:
        fmt = "ros2msg" if connection.msgdef.format.name == "MSG" else "ros2idl"
        self.schema_ids[connection.msgtype] = self.file.add_schema(
            connection.msgtype, fmt, connection.msgdef.data.encode()
        )

    def add_connection(self, connection: Any, offered_qos_profiles: str) -> None:
        self.channel_ids[connection.id] = self.file.add_channel(
            connection.topic,
            "cdr",
            self.schema_ids[connection.msgtype],
            # what rosbag2's MCAP storage (Jazzy) puts beside the QoS: the type's RIHS01 hash
            {"offered_qos_profiles": offered_qos_profiles, "topic_type_hash": connection.digest},
        )

    def write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        self.file.add(self.channel_ids[connection.id], timestamp, data)

    def flush(self, sync: bool = True) -> None:
        """Close the open chunk: its messages in log-time order, then on disk."""
        self.file.flush(sync)

    def close(self, version: int, metadata: str) -> None:
        _ = version
        self.file.add_metadata("rosbag2", {"serialized_metadata": _distro(metadata)})
        for name, rec in self.records.items():
            self.file.add_metadata(name, rec)
        self.file.finish()

    def abort(self) -> None:
        """Close without the summary (complete chunks stay readable for bag recover)."""
        self.file.abort()


ROS_DISTRO = "jazzy"


def _distro(metadata_yaml: str) -> str:
    return metadata_yaml.replace("ros_distro: rosbags", f"ros_distro: {ROS_DISTRO}")


def _qos(topic: str) -> list:
    """The offered QoS of a topic (fluxdrive.io.topics.offered_qos) as rosbags Qos."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    depth, durability = offered_qos(topic)
    inf = QosTime(sec=9223372036, nsec=854775807)  # rmw's "infinite", as rosbag2 records it
    life_s = offered_lifespan_s(topic)
    lifespan = inf if life_s is None else QosTime(sec=int(life_s), nsec=0)
    return [
        Qos(
            QosHistory.KEEP_LAST,
            depth,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL
            if durability == "transient_local"
            else QosDurability.VOLATILE,
            inf,
            lifespan,
            QosLiveliness.AUTOMATIC,
            inf,
            False,
        )
    ]


class BagWriter:
    """The project's one bag writer: a rosbag2 bag (metadata.yaml version 9, `ros_distro:
    jazzy`) with one MCAP file that every MCAP tool opens (see _McapStorage).

    Times: `write(cid, t_ns, data)` takes the message's sample time (sim time from 0, the
    header stamp); the bag's log and publish times are t_ns + `epoch_offset_ns`, by default
    the wall clock at the start minus nothing, so a viewer shows when the run happened.
    The offset is recorded (metadata `epoch_offset_ns`) -- header stamps stay sim time.

    Settings (`settings`: the machine card, observers, scenario; JSON-able) go into
    custom_data "fluxdrive" (rosbag2's place), an MCAP metadata record "fluxdrive", and one
    latched std_msgs/String message on /fluxdrive/settings -- the last survives any
    conversion (rosbags-convert to rosbag1 and back keeps only messages)."""

    def __init__(
        self,
        path: str | Path,
        settings: dict[str, Any] | None = None,
        *,
        epoch_offset_ns: int | None = None,
    ) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        class _Writer(Writer):
            STORAGE_PLUGINS = {StoragePlugin.MCAP: _McapStorage}  # noqa: RUF012

        self.path = Path(path)
        self.offset = time.time_ns() if epoch_offset_ns is None else int(epoch_offset_ns)
        self.store = typestore()
        self.w = _Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.settings = dict(settings or {})
        self.settings.setdefault("epoch_offset_ns", self.offset)
        text = json.dumps(self.settings, default=_json_default)
        self.w.set_custom_data(META_KEY, text)
        self.w.open()
        self.storage: _McapStorage = self.w.storage  # type: ignore[assignment]
        self.storage.records[META_KEY] = {META_KEY: text}
        self.conns: list[Any] = []
        self._channel_of = np.zeros(0, np.int64)  # connection id -> MCAP channel id
        self._settings_cid = self.add_connection(SETTINGS, T_STRING)
        self._settings_msg: bytes | None = self.store.serialize_cdr(
            self.store.types[T_STRING](data=text), T_STRING
        )

    def _settings_at(self, t_log_ns: int) -> None:
        """The settings message, once, at the time of the bag's first data message: a bag
        cut out of a run (a sample bag, a scope capture) then spans its data, as rosbag2
        would record it, not seconds of nothing from t = 0."""
        msg, self._settings_msg = self._settings_msg, None
        if msg is not None:
            self.w.write(self.conns[self._settings_cid], int(t_log_ns), msg)

    def add_connection(self, topic: str, msgtype: str, store: Any = None) -> int:
        """A topic (`store`: a typestore for a type that is not the project's); returns its
        id for `write` (the existing one for a topic added before with the same type)."""
        for i, c in enumerate(self.conns):
            if c.topic == topic and c.msgtype == msgtype:
                return i
        self.conns.append(
            self.w.add_connection(
                topic, msgtype, typestore=store or self.store, offered_qos_profiles=_qos(topic)
            )
        )
        return len(self.conns) - 1

    def write(self, cid: int, t_ns: int, data: bytes | memoryview) -> None:
        if self._settings_msg is not None:
            self._settings_at(t_ns + self.offset)
        self.w.write(self.conns[cid], t_ns + self.offset, data)

    def write_many(
        self, cids: np.ndarray, t_ns: np.ndarray, src: bytes, first: np.ndarray, size: np.ndarray
    ) -> None:
        """Messages in bulk, as `write` one by one would write them: message i is
        src[first[i] : first[i] + size[i]] on connection cids[i] (from add_connection) at
        sample time t_ns[i].  numpy passes, no Python per message (the recorder's writer)."""
        if not len(cids):
            return
        cids = np.asarray(cids, np.int64)
        if len(self._channel_of) < len(self.conns):
            ids = self.storage.channel_ids
            self._channel_of = np.array([ids[c.id] for c in self.conns], np.int64)
        t = np.asarray(t_ns, np.int64) + self.offset
        if self._settings_msg is not None:
            self._settings_at(int(t[0]))  # the first message, as `write` one by one has it
        size = np.asarray(size, np.int64)
        self.storage.file.add_many(
            src, np.asarray(first, np.int64), size, self._channel_of[cids], t
        )
        w = self.w  # rosbags' bookkeeping for metadata.yaml: counts and time range
        for cid, k in enumerate(np.bincount(cids, minlength=len(self.conns)).tolist()):
            if k:
                w.counts[self.conns[cid].id] += k
        w.min_timestamp = min(w.min_timestamp, int(t.min()))
        w.max_timestamp = max(w.max_timestamp, int(t.max()))

    def flush(self, sync: bool = True) -> None:
        """Close the open chunk and push the file to the disk (crash safety)."""
        self.storage.flush(sync)

    def close(self) -> None:
        self._settings_at(self.offset)  # a bag without data: the settings at t = 0
        self.w.close()
        meta = self.path / "metadata.yaml"
        meta.write_text(_distro(meta.read_text()))

    def abort(self) -> None:
        self.w.abort()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, *_) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return str(x)


MODEL_KEYS = ("r_hat_ohm", "l_hat_h", "lambda_hat_vs")


def observer_model_of(sc) -> dict[str, float]:
    """The observer model (R^, L^, lambda^) a run's observers start from: the machine card
    times the bench's model errors.  A variant replayed over the run's bag takes it by
    default (fluxdrive.replay.lab), so it sees what the recorded observers saw."""

    cfg = sc.bench.apply_observer_model(ObserverConfig(), sc.machine)
    card = sc.machine
    return {
        "r_hat_ohm": float(card.resistance_ohm if cfg.r_hat_ohm is None else cfg.r_hat_ohm),
        "l_hat_h": float(card.inductance_h if cfg.l_hat_h is None else cfg.l_hat_h),
        "lambda_hat_vs": float(
            card.flux_linkage_vs if cfg.lambda_hat_vs is None else cfg.lambda_hat_vs
        ),
    }


def recorded_observer_model(meta: dict[str, Any]) -> tuple[dict[str, float] | None, str]:
    """The observer model a bag's settings record, and where it came from: the settings'
    `observer_model`, else (older bags) the driving -- or first -- recorded observer's
    R^, L^, lambda^; (None, reason) when the bag records none."""
    om = meta.get("observer_model")
    if isinstance(om, dict) and all(isinstance(om.get(k), (int, float)) for k in MODEL_KEYS):
        return {k: float(om[k]) for k in MODEL_KEYS}, "the bag's settings (observer_model)"
    configs = meta.get("observers") or {}
    for nm in [meta.get("driving"), *sorted(configs)]:
        cfg = configs.get(nm) if isinstance(nm, str) else None
        if isinstance(cfg, dict) and all(isinstance(cfg.get(k), (int, float)) for k in MODEL_KEYS):
            return {k: float(cfg[k]) for k in MODEL_KEYS}, f"the recorded observer '{nm}'"
    return None, "the machine card (the bag records no observer model)"


def run_metadata(
    result,
    k0: int = 0,
    obs_states: dict[str, list[float]] | None = None,
    observers: list[str] | None = None,
) -> dict[str, Any]:
    sc = result.scenario
    names = result.names if observers is None else observers
    return {
        "format": 1,
        "machine": asdict(sc.machine),
        "observers": {nm: sc.observers[nm].to_dict() for nm in names if nm in sc.observers},
        "observer_model": observer_model_of(sc),
        "driving": result.driving,
        "scenario": {
            "name": sc.name,
            "source": sc.source,
            "seed": sc.seed,
            "duration_s": sc.duration_s,
            "steady_window_s": list(sc.steady_window_s),
            "step_load_time_s": sc.step_load_time_s,
        },
        "first_seq": int(k0),
        "observer_states": obs_states or {},
    }


def write_run_bag(
    result,
    path: str | Path,
    *,
    start_s: float = 0.0,
    end_s: float | None = None,
    observers: list[str] | None = None,
    truth: bool = True,
    ctrl: bool = True,
    duty: bool = True,
    epoch_offset_ns: int | None = None,
    obs_states: dict[str, list[float]] | None = None,
    extra_meta: dict[str, Any] | None = None,
) -> Path:
    """Write a SimResult (or a replay's arrays with the same fields) as a rosbag2/mcap bag.

    start_s/end_s cut a window out of the run; `obs_states` (observer name -> OS_* state
    at the first written frame) lets a replay of a cut bag reproduce the estimates.
    """
    path = Path(path)
    t = result.t
    k0 = int(np.searchsorted(t, start_s - 1e-12))
    k1 = len(t) if end_s is None else int(np.searchsorted(t, end_s - 1e-12))
    names = list(result.names if observers is None else observers)
    meta = run_metadata(result, k0, obs_states, names)
    if extra_meta:
        meta.update(extra_meta)
    fw = messages.FrameWire(extra_flags=messages.STATUS_SIMULATED)
    tw = messages.TruthWire()
    cw = messages.ControlWire()
    with BagWriter(path, meta, epoch_offset_ns=epoch_offset_ns) as w:
        c_fr = w.add_connection(TOPIC_FRAME, T_FRAME)
        c_tr = w.add_connection(TOPIC_TRUTH, T_TRUTH) if truth else None
        c_co = w.add_connection(TOPIC_CTRL, T_CTRL) if ctrl else None
        c_du = w.add_connection(TOPIC_DUTY, T_DUTY) if duty else None
        c_es = [
            (
                result.names.index(nm),
                messages.EstimateWire(nm),
                w.add_connection(est_topic(nm), T_EST),
            )
            for nm in names
        ]
        for k in range(k0, k1):
            t_ns = int(round(t[k] * 1e9))
            st = divmod(t_ns, 1_000_000_000)
            seq = int(result.frames[k, FR_SEQ])
            w.write(c_fr, t_ns, fw.pack(result.frames[k], *st))
            if c_tr is not None:
                w.write(c_tr, t_ns, tw.pack(result.truth[k], seq, *st))
            for i, ew, c in c_es:
                w.write(c, t_ns, ew.pack(result.est[i, k], seq, *st))
            if c_co is not None:
                w.write(c_co, t_ns, cw.pack_state(result.ctrl[k], seq, *st))
            if c_du is not None:
                w.write(c_du, t_ns, cw.pack_duty(result.ctrl[k], seq, *st))
    return path


# ------------------------------------------------------------------ reading
@dataclass
class RunBag:
    path: Path
    t: np.ndarray  # (N,) frame stamps [s]
    frames: np.ndarray  # (N, FR_N), ordered by seq
    truth: np.ndarray | None  # (N, TR_N) aligned with frames, NaN rows where missing
    est: dict[str, np.ndarray]  # observer name -> (N, ES_N) aligned, NaN where missing
    ctrl: np.ndarray | None  # (N, CO_N) aligned
    meta: dict[str, Any]
    counts: dict[str, int]  # topic -> messages read
    problems: list[str] = field(default_factory=list)  # what was missing / damaged
    raw_frames: list[tuple[int, bytes]] = field(default_factory=list)  # (t_ns, CDR) for --live
    matched: dict[str, int] = field(default_factory=dict)  # topic -> frames it has a message for
    # the parameter markers of the bag's graph, in recording order (read_markers)
    markers: list[dict[str, Any]] = field(default_factory=list)

    @property
    def n(self) -> int:
        return len(self.frames)

    def machine(self, override: MachineCard | None = None) -> MachineCard:
        if override is not None:
            return override
        m = self.meta.get("machine")
        if m:
            known = {f.name for f in fields(MachineCard)}
            return MachineCard(**{k: v for k, v in m.items() if k in known})
        card = MachineCard()
        if len(self.t) > 2:  # no card recorded: take the PWM rate from the stamps
            dt = float(np.median(np.diff(self.t)))
            if dt > 0:
                card = MachineCard(pwm_hz=round(1.0 / dt, 6))
        return card


def _bag_files(path: Path) -> list[Path]:
    return sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3")) + sorted(path.glob("*.zstd"))


def _info(path: Path) -> dict[str, Any]:
    try:
        info = yamlio.load_file(path / "metadata.yaml") or {}
    except Exception as exc:  # noqa: BLE001
        raise BagError(f"{path}: unreadable metadata.yaml ({_one_line(exc)})") from None
    if not isinstance(info, dict) or "rosbag2_bagfile_information" not in info:
        raise BagError(f"{path}: metadata.yaml is not rosbag2 bag information")
    return info["rosbag2_bagfile_information"] or {}


def _indexed_source(path: Path):
    """rosbags AnyReader: (topics, message iterator, close, the bag's definitions)."""
    from rosbags.highlevel import AnyReader

    reader = AnyReader([path])
    reader.open()
    topics = {c.topic: c.msgtype for c in reader.connections}
    defs = {c.topic: getattr(c.msgdef, "data", None) for c in reader.connections}
    conns = [c for c in reader.connections if _wanted(c.topic, c.msgtype)]

    def it():
        for c, t_ns, data in reader.messages(connections=conns):
            yield c.topic, c.msgtype, t_ns, data

    return topics, it(), reader.close, defs


def _stream_source(path: Path):
    """Sequential mcap reader for a bag without a usable index (recording cut off): reads
    records until the data ends or breaks."""
    import io

    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    files = _bag_files(path)
    f = files[0]
    if f.name.endswith(".zstd"):
        try:
            from compression import zstd  # type: ignore[import-not-found]
        except ImportError:
            from backports import zstd  # type: ignore[import-not-found,no-redef]
        raw = f.read_bytes()
        dec = zstd.ZstdDecompressor()
        try:
            data = dec.decompress(raw)
        except Exception:  # noqa: BLE001 - keep what decompressed
            data = b""
        stream: Any = io.BytesIO(data)
    elif f.suffix == ".mcap":
        stream = io.BytesIO(f.read_bytes())
    else:
        raise BagError(f"{path}: cannot open {f.name} (damaged sqlite3 storage)")
    schemas: dict[int, str] = {}
    schema_text: dict[int, str] = {}
    chans: dict[int, tuple[str, str]] = {}
    topics: dict[str, str] = {}
    defs: dict[str, str | None] = {}
    # read the records up front (small bags; the reader keeps no index)
    msgs: list[tuple[str, str, int, bytes]] = []
    err = None
    try:
        for rec in StreamReader(stream, emit_chunks=False).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec.name
                schema_text[rec.id] = bytes(rec.data).decode(errors="replace")
            elif isinstance(rec, Channel):
                ty = schemas.get(rec.schema_id, "")
                chans[rec.id] = (rec.topic, ty)
                topics[rec.topic] = ty
                defs[rec.topic] = schema_text.get(rec.schema_id)
            elif isinstance(rec, Message) and rec.channel_id in chans:
                tp, ty = chans[rec.channel_id]
                if _wanted(tp, ty):
                    msgs.append((tp, ty, rec.log_time, rec.data))
    except Exception as exc:  # noqa: BLE001
        err = exc

    def it():
        yield from msgs
        if err is not None:
            raise EOFError(f"data ends after {len(msgs)} readable messages ({_one_line(err)})")

    return topics, it(), lambda: None, defs


def _wanted(topic: str, msgtype: str) -> bool:
    return (
        (topic == TOPIC_FRAME and msgtype == T_FRAME)
        or (topic == TOPIC_TRUTH and msgtype == T_TRUTH)
        or (topic == TOPIC_CTRL and msgtype == T_CTRL)
        or (topic == TOPIC_DUTY and msgtype == T_DUTY)
        or (topic == SETTINGS and msgtype == T_STRING)
        or (topic == MARKER and msgtype == T_MARKER)
        or (topic.startswith(EST_PREFIX) and topic.endswith(EST_SUFFIX) and msgtype == T_EST)
    )


def _bag_folder(path: Path) -> Path:
    """The rosbag2 folder `path` names (a bare .mcap file: its folder), checked to hold a
    storage file."""
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    if path.is_file():  # a bare .mcap file: use its folder if that is a bag
        if (path.parent / "metadata.yaml").exists():
            path = path.parent
        else:
            raise BagError(f"{path}: not a rosbag2 folder (no metadata.yaml next to it)")
    if not (path / "metadata.yaml").exists():
        raise BagError(f"{path}: not a rosbag2 bag (no metadata.yaml)")
    return path


def _recorded_meta(info: dict[str, Any], problems: list[str]) -> dict[str, Any]:
    """The recorder's settings stored in metadata.yaml's custom data ({} when absent)."""
    try:
        cd = info.get("custom_data") or {}
        if META_KEY in cd:
            return json.loads(cd[META_KEY])
    except Exception:  # noqa: BLE001
        problems.append("unreadable fluxdrive metadata (ignored)")
    return {}


def _expected_counts(info: dict[str, Any]) -> dict[str, int]:
    """Messages per wanted topic that metadata.yaml says the bag holds."""
    expected: dict[str, int] = {}
    for tm in info.get("topics_with_message_count") or []:
        try:
            md = tm["topic_metadata"]
            if _wanted(md["name"], md["type"]):
                expected[md["name"]] = int(tm["message_count"])
        except (KeyError, TypeError, ValueError):
            pass
    return expected


def _open_source(path: Path, problems: list[str]):
    """The indexed reader, or the sequential one when the index is unreadable (a recording
    cut off): (topics, message iterator, close, definitions)."""
    try:
        return _indexed_source(path)
    except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds; name the problem
        first = f"{type(exc).__name__}: {_one_line(exc)}"
    try:
        topics, messages_, close, defs = _stream_source(path)
    except BagError:
        raise
    except Exception:  # noqa: BLE001
        raise BagError(f"{path}: cannot open bag ({first}); not a readable rosbag2 bag") from None
    if not topics:
        raise BagError(
            f"{path}: cannot open bag ({first}); storage holds no readable "
            f"records (truncated or damaged)"
        ) from None
    problems.append(f"bag index unreadable ({first}): storage truncated, read sequentially")
    return topics, messages_, close, defs


def _check_frame_topic(path: Path, topics: dict[str, str]) -> None:
    """One line naming why the bag holds no frames to replay."""
    if not topics:
        raise BagError(f"{path}: bag is empty (no topics)")
    if TOPIC_FRAME not in topics:
        ours = [tp for tp, ty in topics.items() if ty.startswith("flux_drive_msgs/")]
        if not ours:
            raise BagError(
                f"{path}: no fluxdrive topics; bag holds foreign message types "
                f"{sorted(set(topics.values()))[:4]}"
            )
        raise BagError(f"{path}: no {TOPIC_FRAME} topic (bag has {sorted(topics)})")
    if topics[TOPIC_FRAME] != T_FRAME:
        raise BagError(f"{path}: {TOPIC_FRAME} has type {topics[TOPIC_FRAME]}, expected {T_FRAME}")


@dataclass
class _RawMessages:
    """What the reader returned, per topic, before decoding."""

    counts: dict[str, int] = field(default_factory=dict)
    raws: dict[str, list[bytes]] = field(default_factory=dict)
    frames: list[tuple[int, bytes]] = field(default_factory=list)  # (t_ns, CDR) if kept


def _read_messages(path: Path, source, keep_raw: bool, problems: list[str]) -> _RawMessages:
    """Every wanted message's bytes, up to where the storage ends or breaks; the reader is
    closed in any case."""
    topics, messages_, close, _ = source
    got = _RawMessages()
    try:
        _check_frame_topic(path, topics)
        try:
            for tp, _msgtype, t_ns, data in messages_:
                got.counts[tp] = got.counts.get(tp, 0) + 1
                got.raws.setdefault(tp, []).append(bytes(data))
                if keep_raw and tp == TOPIC_FRAME:
                    got.frames.append((t_ns, got.raws[tp][-1]))
        except Exception as exc:  # noqa: BLE001
            problems.append(
                f"bag truncated or damaged after {sum(got.counts.values())} messages "
                f"({type(exc).__name__}: {_one_line(exc)})"
            )
    finally:
        try:
            close()
        except Exception:  # noqa: BLE001
            pass
    return got


@dataclass
class _FrameIndex:
    """The frames replayed (the last of each seq, in seq order) and their stamps."""

    seqs: np.ndarray
    frames: np.ndarray
    t: np.ndarray

    @property
    def n(self) -> int:
        return len(self.seqs)


def _frame_index(path: Path, tables: dict[str, tuple], problems: list[str]) -> _FrameIndex:
    """The frame rows by seq; duplicates and gaps named in `problems`."""
    if TOPIC_FRAME not in tables or not len(tables[TOPIC_FRAME][0]):
        raise BagError(
            f"{path}: no readable {TOPIC_FRAME} messages "
            + (f"({problems[-1]})" if problems else "(topic is empty)")
        )
    fseq, frows, fcols = tables[TOPIC_FRAME]
    seqs, last = _last_of_each(fseq)
    n = len(seqs)
    t = (
        fcols["header.stamp.sec"][last].astype(np.int64) * 1_000_000_000
        + fcols["header.stamp.nanosec"][last].astype(np.int64)
    ).astype(np.float64) * 1e-9
    if len(fseq) > n:  # one seq recorded more than once: not one graph's one run
        back = int(np.count_nonzero(np.diff(fseq.astype(np.int64)) <= 0))
        problems.append(
            f"{len(fseq) - n} duplicate frames (a seq recorded more than once; "
            f"{back} times the seq did not advance in recording order): frames of "
            f"another graph on the same ROS domain, or a restarted source; the "
            f"last of each seq replayed"
        )
    span = int(seqs[-1] - seqs[0] + 1)
    if span > n:
        problems.append(
            f"{span - n} of {span} frames missing (seq gaps); replaying the "
            f"{n} present back to back"
        )
    return _FrameIndex(seqs, frows[last], t)


def _align(
    tables: dict[str, tuple],
    index: _FrameIndex,
    tp: str,
    width: int,
    matched: dict[str, int],
    problems: list[str] | None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Topic `tp`'s rows placed at their frame's seq (NaN where none arrived) and which
    frames have one; the count goes to `matched`, the shortfall to `problems` if given."""
    if tp not in tables or not len(tables[tp][0]):
        return None
    n, seqs = index.n, index.seqs
    mseq, mrows, _ = tables[tp]
    out = np.full((n, width), np.nan)
    pos = np.searchsorted(seqs, mseq)
    hit = (pos < n) & (seqs[np.minimum(pos, n - 1)] == mseq)
    out[pos[hit]] = mrows[hit]
    have = np.zeros(n, dtype=bool)
    have[pos[hit]] = True
    matched[tp] = int(have.sum())
    if problems is not None and not have.all():
        problems.append(f"{tp}: {int(n - have.sum())} of {n} frames have no matching message")
    return out, have


def _controller_rows(
    state: tuple[np.ndarray, np.ndarray] | None,
    duty: tuple[np.ndarray, np.ndarray] | None,
    n: int,
) -> np.ndarray | None:
    """One CO_* row from both messages; a row where only one arrived keeps 0 in the other's
    columns (the replay reads mode/fault and the speed reference from it). Duties alone
    carry no controller state: None."""
    if state is None:
        return None
    ctrl = np.full((n, CO_N), np.nan)
    have = np.zeros(n, dtype=bool)
    for part, cols in (
        (duty, [c for _, c in messages.DUTY_MAP]),
        (state, [c for _, c in messages.STATE_MAP]),
    ):
        if part is not None:
            idx = np.ix_(part[1], np.asarray(cols))
            ctrl[idx] = part[0][idx]
            have |= part[1]
    ctrl[have] = np.nan_to_num(ctrl[have])
    return ctrl


def read_run_bag(path: str | Path, keep_raw: bool = False) -> RunBag:
    """Read a drive bag into aligned arrays.  Raises BagError (one line) for a bag that
    holds nothing replayable; a damaged or partial bag returns what it holds, with the
    damage listed in `problems`."""
    path = _bag_folder(Path(path))
    info = _info(path)
    if not _bag_files(path):
        raise BagError(f"{path}: bag has no storage file (.mcap/.db3)")
    problems: list[str] = []
    meta = _recorded_meta(info, problems)
    expected = _expected_counts(info)
    source = _open_source(path, problems)
    topics, defs = source[0], source[3]
    got = _read_messages(path, source, keep_raw, problems)
    if "machine" not in meta:  # converted bag: metadata.yaml lost custom_data
        meta = {**meta, **_settings_elsewhere(path, got.raws.get(SETTINGS))}
        if "machine" not in meta:
            problems.append(
                "bag carries no recorder settings (machine card, observers): "
                "replaying with the default machine card and observers"
            )
    got.raws.pop(SETTINGS, None)
    marker_raws = got.raws.pop(MARKER, [])
    # each topic decoded with the layout the bag recorded (a bag from before a field was
    # added still reads)
    tables = {
        tp: decode_rows(topics[tp], r, problems, tp, defs.get(tp)) for tp, r in got.raws.items()
    }
    graph_id, keep_frames = _own_graph(tables, meta, problems)
    raw = got.frames
    if keep_raw and keep_frames is not None and len(raw) == len(keep_frames):
        raw = [r for r, k in zip(raw, keep_frames, strict=True) if k]
    index = _frame_index(path, tables, problems)
    for tp, want in expected.items():
        if want > got.counts.get(tp, 0):
            have = got.counts.get(tp, 0)
            problems.append(f"{tp}: {have} of {want} messages read ({want - have} missing)")
    matched: dict[str, int] = {TOPIC_FRAME: index.n}
    truth = None
    if (a := _align(tables, index, TOPIC_TRUTH, TR_N, matched, problems)) is not None:
        truth = a[0]
        truth[:, TR_T] = index.t
    ctrl = _controller_rows(
        _align(tables, index, TOPIC_CTRL, CO_N, matched, problems),
        _align(tables, index, TOPIC_DUTY, CO_N, matched, None),
        index.n,
    )
    est = {}
    for tp in tables:
        if tp.startswith(EST_PREFIX) and tp.endswith(EST_SUFFIX):
            e = _align(tables, index, tp, ES_N, matched, problems)
            if e is not None:
                est[tp[len(EST_PREFIX) : -len(EST_SUFFIX)]] = e[0]
    markers = read_markers(marker_raws, graph_id, problems, defs.get(MARKER))
    bag = RunBag(path, index.t, index.frames, truth, est, ctrl, meta, got.counts, problems)
    bag.raw_frames, bag.matched, bag.markers = raw, matched, markers
    return bag


def read_markers(
    raws: list[bytes],
    graph_id: int | None = None,
    problems: list[str] | None = None,
    definition: str | None = None,
) -> list[dict[str, Any]]:
    """ParameterMarker messages -> dicts (seq, graph_id, node, name, value, successful,
    reason, source), those of another graph than `graph_id` left out (id 0: a tool outside
    any launch, kept).  A marker that does not decode is named in `problems`."""
    layout = layout_type(T_MARKER, definition)
    dec = Decoder(layout)
    out = []
    for data in raws:
        try:
            strings = read_strings(layout, data)
            c = dec.codec_for(data)
            nums = dict(zip(c.fields, c.unpack(data), strict=True))
        except Exception as exc:  # noqa: BLE001 - a damaged marker: name it, keep the rest
            if problems is not None:
                problems.append(f"undecodable {MARKER} message ({_one_line(exc)})")
            continue
        gid = int(nums.get("graph_id", 0))
        if graph_id is not None and gid not in (0, graph_id):
            continue
        out.append(
            {
                "seq": int(nums.get("seq", 0)),
                "graph_id": gid,
                "node": strings.get("node", ""),
                "name": strings.get("name", ""),
                "value": strings.get("value", ""),
                "successful": bool(nums.get("successful", False)),
                "reason": strings.get("reason", ""),
                "source": strings.get("source", ""),
            }
        )
    return out


def _settings_elsewhere(path: Path, settings_msgs: list[bytes] | None) -> dict[str, Any]:
    """The recorder's settings when metadata.yaml has none (a converted bag): the MCAP
    metadata record "fluxdrive", else the /fluxdrive/settings message."""
    for f in sorted(path.glob("*.mcap")):
        try:
            from mcap.reader import make_reader

            with f.open("rb") as fh:
                for rec in make_reader(fh).iter_metadata():
                    if rec.name == META_KEY and META_KEY in rec.metadata:
                        return json.loads(rec.metadata[META_KEY])
        except Exception:  # noqa: BLE001 - no summary / not ours: try the message
            pass
    for data in settings_msgs or []:
        try:
            return json.loads(read_strings(T_STRING, data)["data"])
        except Exception:  # noqa: BLE001
            continue
    return {}


def _own_graph(
    tables: dict, meta: dict, problems: list[str]
) -> tuple[int | None, np.ndarray | None]:
    """Keep only the messages of the bag's own graph (graph_id: the recorder's, from the
    settings; else the id most frames carry) -- a recorder on a shared domain of an older
    version, or a bag merged from two, may hold another graph's messages.  Drops the others
    from `tables` in place and names them in `problems`; returns the id and the frames' keep
    mask (None when nothing was dropped or the bag predates graph_id)."""
    fr = tables.get(TOPIC_FRAME)
    if fr is None or "graph_id" not in fr[2] or not len(fr[0]):
        return None, None
    ids = fr[2]["graph_id"].astype(np.uint64)
    gid = meta.get("graph_id")
    if gid is None:
        u, c = np.unique(ids, return_counts=True)
        gid = int(u[np.argmax(c)])
    gid = np.uint64(int(gid))
    dropped: dict[str, int] = {}
    keep_frames = None
    for tp, (seq, rows, cols) in list(tables.items()):
        if "graph_id" not in cols:
            continue
        keep = cols["graph_id"].astype(np.uint64) == gid
        if keep.all():
            continue
        dropped[tp] = int((~keep).sum())
        tables[tp] = (seq[keep], rows[keep], {k: v[keep] for k, v in cols.items()})
        if tp == TOPIC_FRAME:
            keep_frames = keep
    if dropped:
        others = sorted({int(i) for i in ids[ids != gid]})
        problems.append(
            f"{sum(dropped.values())} messages of another graph dropped ("
            + ", ".join(f"{tp} {n}" for tp, n in dropped.items())
            + f"; this bag's graph_id {int(gid)}, others {others[:3]}"
            + (" ..." if len(others) > 3 else "")
            + ")"
        )
    return int(gid), keep_frames


def _last_of_each(seq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique seqs and, for each, the index of its last message (a repeated seq:
    the later message wins)."""
    rev = seq[::-1]
    u, first_in_rev = np.unique(rev, return_index=True)
    return u, len(seq) - 1 - first_in_rev


def columns(mtype: str, raws: list[bytes]) -> dict[str, np.ndarray]:
    """Decode many serialised messages of one type at once: {field path: array} over the
    numeric fields.  Messages are grouped by layout (size and string lengths), each group
    read with one numpy structured view (about 3 s per million messages)."""
    dec = Decoder(mtype)
    by_len: dict[int, list[int]] = {}
    for i, r in enumerate(raws):
        by_len.setdefault(len(r), []).append(i)
    n = len(raws)
    cols: dict[str, np.ndarray] = {}
    for _, idx in by_len.items():
        size = len(raws[idx[0]])  # DDS may pad a message to a multiple of 4 bytes
        layouts: dict[tuple, list[int]] = {}
        codecs: dict[tuple, Any] = {}
        for i in idx:
            c = dec.layout_of(raws[i])
            key = (c.type_name, tuple(sorted(c.strings.items())))
            layouts.setdefault(key, []).append(i)
            codecs[key] = c
        for key, g in layouts.items():
            codec = codecs[key]
            arr = np.frombuffer(
                b"".join(raws[i] for i in g), dtype=codec.numpy_dtype(itemsize=size)
            )
            sel = np.asarray(g)
            for j, fpath in enumerate(codec.fields):
                col = cols.get(fpath)
                if col is None:
                    col = cols[fpath] = np.zeros(
                        n, dtype=np.float64 if arr[f"f{j}"].dtype.kind == "f" else np.int64
                    )
                col[sel] = arr[f"f{j}"]
    return cols


def decode_rows(
    mtype: str,
    raws: list[bytes],
    problems: list[str] | None = None,
    topic: str = "",
    definition: str | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Messages of one type -> (seq (M,), engine rows (M, width), columns), by the one
    mapping (fluxdrive.io.messages); unmapped row columns are NaN.  A message that does not
    decode is skipped and named in `problems`."""
    mapping, width = messages.MAPS.get(mtype, ((), 0))
    layout = layout_type(mtype, definition)  # `definition`: the bag's own text of mtype
    good = raws
    try:
        cols = columns(layout, good)
    except Exception as exc:  # noqa: BLE001 - damaged payloads: message by message
        cols, good = _columns_one_by_one(layout, good, problems, topic, exc)
    m = len(good)
    rows = np.full((m, width), np.nan)
    for fpath, c in mapping:
        if fpath in cols:
            rows[:, c] = cols[fpath]
    messages.post_read(mtype, rows)
    seq = cols["seq"].astype(np.int64) if "seq" in cols else np.zeros(m, dtype=np.int64)
    if mtype == T_FRAME:
        rows[:, FR_SEQ] = seq
    return seq, rows, cols


def _columns_one_by_one(mtype, raws, problems, topic, first_exc):
    ok = []
    for r in raws:
        try:
            Decoder(mtype).decode(r)
            ok.append(r)
        except Exception as exc:  # noqa: BLE001
            if problems is not None:
                problems.append(f"undecodable {topic} message ({_one_line(exc)})")
    return columns(mtype, ok), ok


def load_run_arrays(bag: str | Path, ts_s: float, names: list[str] | None = None) -> dict[str, Any]:
    """A run's bag -> engine arrays indexed by seq (what fluxdrive.analysis.metrics takes,
    the layout of fluxdrive.drive.sim.SimResult): frames (N, FR_N), truth (N, TR_N),
    est (n_obs, N, ES_N), ctrl (N, CO_N); N = last frame seq + 1, rows of samples missing
    from the bag NaN (`missing` counts them per topic).  Read by read_run_bag."""
    rb = read_run_bag(bag)
    seqs = rb.frames[:, FR_SEQ].astype(np.int64)
    n = int(seqs.max()) + 1 if len(seqs) else 0
    names = list(names) if names is not None else sorted(rb.est)

    def by_seq(rows: np.ndarray | None, width: int) -> np.ndarray:
        out = np.full((n, width), np.nan)
        if rows is not None:
            out[seqs] = rows
        return out

    frames = by_seq(rb.frames, FR_N)
    truth = by_seq(rb.truth, TR_N)
    truth[:, TR_T] = np.arange(n) * ts_s
    truth[np.isnan(truth[:, TR_THETA_E]), TR_T] = np.nan  # a sample the bag lacks
    est = (
        np.stack([by_seq(rb.est.get(nm), ES_N) for nm in names])
        if names
        else np.full((0, n, ES_N), np.nan)
    )
    ctrl = by_seq(rb.ctrl, CO_N)
    nf = len(seqs)
    have = rb.matched
    return {
        "n": n,
        "frames": frames,
        "truth": truth,
        "est": est,
        "ctrl": ctrl,
        "names": names,
        "missing": {
            "frame": n - nf,
            "truth": n - have.get(TOPIC_TRUTH, 0),
            **{f"estimate/{nm}": n - have.get(est_topic(nm), 0) for nm in names},
            "duty": n - have.get(TOPIC_DUTY, 0),
            "controller_state": n - have.get(TOPIC_CTRL, 0),
        },
    }


def read_raw(bag: str | Path, topic_filter=None):
    """Yield (topic, msgtype, log time [ns], CDR bytes) of a bag in log order."""
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
        conns = [c for c in reader.connections if topic_filter is None or topic_filter(c.topic)]
        for conn, ts, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, ts, raw


def topic_counts(bag: str | Path) -> dict[str, int]:
    """Messages per topic (from the bag's index)."""
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
        out: dict[str, int] = {}
        for c in reader.connections:
            out[c.topic] = out.get(c.topic, 0) + c.msgcount
        return out


def _one_line(exc: BaseException) -> str:
    s = str(exc).strip().splitlines()
    return (s[0] if s else type(exc).__name__)[:200]


__all__ = [
    "BagError",
    "RunBag",
    "read_run_bag",
    "write_run_bag",
    "typestore",
    "est_topic",
    "TOPIC_FRAME",
    "TOPIC_TRUTH",
    "TOPIC_DUTY",
    "TOPIC_CTRL",
]


def observer_states_at(result, k0: int) -> dict[str, list[float]]:
    """The recorded observers' OS_* states just before frame k0, by re-running each over
    frames 0..k0-1 (the same compiled kernel as the run, so the same numbers): stored in a
    cut-out bag so that replaying it continues the live estimates exactly."""

    out: dict[str, list[float]] = {}
    for nm in result.names:
        cfg = result.scenario.observers.get(nm)
        if cfg is None:
            continue
        obs = KernelObserver(cfg, result.scenario.machine, name=nm)
        obs.reset()
        if k0 > 0:
            obs.run(result.frames[:k0])
        out[nm] = [float(x) for x in obs.state]
    return out


def bag_counts(bag: Path) -> tuple[dict[str, int], dict[str, int]]:
    """Per-topic message counts from the mcap summary and from metadata.yaml."""
    from mcap.reader import make_reader

    mcap_counts: dict[str, int] = {}
    for f in sorted(bag.glob("*.mcap")):
        with open(f, "rb") as fh:
            summ = make_reader(fh).get_summary()
            if summ is None or summ.statistics is None:
                raise RuntimeError(f"{f}: no summary section (bag not finalised)")
            for ch in summ.channels.values():  # a channel with no message has no count entry
                mcap_counts.setdefault(ch.topic, 0)
            for cid, n in summ.statistics.channel_message_counts.items():
                topic = summ.channels[cid].topic
                mcap_counts[topic] = mcap_counts.get(topic, 0) + n
    meta = yamlio.load_file(bag / "metadata.yaml")["rosbag2_bagfile_information"]
    meta_counts = {
        t["topic_metadata"]["name"]: int(t["message_count"])
        for t in meta["topics_with_message_count"]
    }
    return mcap_counts, meta_counts


MISSING_KEY = "fluxdrive_missing"  # custom_data key: JSON, what a bag lacks and why
CAN_LINK_KEY = "fluxdrive_can_link"  # custom_data key: JSON, the bench bridge's link counts


def last_status(bag: str | Path, name_prefix: str) -> dict[str, str]:
    """The values of the last DiagnosticStatus named `name_prefix`... a bag recorded on
    /diagnostics ({} if none): a node's counters as it last reported them."""
    ts = typestore()
    out: dict[str, str] = {}
    for _topic, mt, _t, raw in read_raw(bag, lambda t: t.endswith("/diagnostics")):
        for st in ts.deserialize_cdr(raw, mt).status:
            if st.name.startswith(name_prefix):
                out = {kv.key: kv.value for kv in st.values}
    return out


def note_custom(bag: Path, key: str, data: dict[str, Any]) -> bool:
    """Add `data` (JSON) to a finalised bag's metadata.yaml as custom_data `key`; False if
    the metadata cannot be read or written (the caller says so in its log)."""
    f = Path(bag) / "metadata.yaml"
    try:
        meta = yamlio.load_file(f)
        info = meta["rosbag2_bagfile_information"]
        custom = info.get("custom_data") or {}
        custom[key] = json.dumps(data)
        info["custom_data"] = custom
        f.write_text(yamlio.dumps(meta, sort_keys=False))
    except (OSError, ValueError, yamlio.YAMLError, KeyError, TypeError, AttributeError):
        return False
    return True


def note_missing(
    bag: Path,
    missing: dict[str, dict[str, int]],
    why: str,
    lost_in_transit: dict[str, int] | None = None,
) -> None:
    """Add to a finalised bag's metadata.yaml (custom_data `fluxdrive_missing`, JSON) what
    it lacks -- {topic: {"recorded": r, "published": n}} and messages lost in transit --
    and why, so that whoever reads the bag later sees it.  Notes from several checkers (the
    recorder, the launcher) are merged.  A metadata file that cannot be read or written is
    left alone: the caller has said it in its log."""
    f = Path(bag) / "metadata.yaml"
    try:
        meta = yamlio.load_file(f)
        info = meta["rosbag2_bagfile_information"]
        custom = info.get("custom_data") or {}
        note = json.loads(custom.get(MISSING_KEY) or "{}")
        note.setdefault("topics", {}).update(missing)
        if lost_in_transit:
            note.setdefault("lost_in_transit", {}).update(lost_in_transit)
        if why not in note.setdefault("why", []):
            note["why"].append(why)
        custom[MISSING_KEY] = json.dumps(note)
        info["custom_data"] = custom
        f.write_text(yamlio.dumps(meta, sort_keys=False))
    except (OSError, ValueError, yamlio.YAMLError, KeyError, TypeError, AttributeError):
        pass
