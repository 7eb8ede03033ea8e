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
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.core.machine import ConfigError, MachineCard
from fluxdrive.drive.control import (
    CO_DA,
    CO_EN,
    CO_FAULT,
    CO_ID,
    CO_ID_REF,
    CO_IQ,
    CO_IQ_REF,
    CO_MODE,
    CO_N,
    CO_TH,
    CO_VD,
    CO_VQ,
    CO_W_FB,
    CO_W_REF,
    MODE_FAULT,
)
from fluxdrive.drive.observers import (
    ES_EA,
    ES_EB,
    ES_ERR,
    ES_LA,
    ES_LB,
    ES_N,
    ES_TH,
    ES_VALID,
    ES_W,
)
from fluxdrive.drive.plant import (
    FR_DA,
    FR_EN,
    FR_ENC,
    FR_FLAGS,
    FR_IA,
    FR_N,
    FR_SEQ,
    FR_VAB,
    FR_VDC,
    TR_IA,
    TR_N,
    TR_T,
    TR_TE,
    TR_THETA_E,
    TR_TL,
    TR_WM,
)
from fluxdrive.io.topics import (
    CONTROLLER_STATE,
    DUTY,
    ESTIMATE,
    FRAME,
    MSG_SRC_DIR,
    OBS_NAMESPACE,
    T_DUTY,
    T_ESTIMATE,
    T_FRAME,
    T_STATE,
    T_TRUTH,
    TRUTH,
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


# ------------------------------------------------------------------ row <-> message
def _stamp(store, t_ns: int):
    Time = store.types["builtin_interfaces/msg/Time"]
    return store.types["std_msgs/msg/Header"](
        stamp=Time(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)),
        frame_id="")


def frame_msg(store, fr: np.ndarray, t_ns: int):
    return store.types[T_FRAME](
        header=_stamp(store, t_ns), seq=int(fr[FR_SEQ]),
        i_abc=np.array(fr[FR_IA:FR_IA + 3], dtype=np.float64),
        v_ll=np.array(fr[FR_VAB:FR_VAB + 3], dtype=np.float64),
        vdc=float(fr[FR_VDC]),
        duty_applied=np.array(fr[FR_DA:FR_DA + 3], dtype=np.float64),
        pwm_enabled=bool(fr[FR_EN] > 0.5), encoder_counts=float(fr[FR_ENC]),
        status_flags=int(fr[FR_FLAGS]) | 2)  # STATUS_SIMULATED


def frame_row(m) -> np.ndarray:
    fr = np.zeros(FR_N)
    fr[FR_IA:FR_IA + 3] = m.i_abc
    fr[FR_VAB:FR_VAB + 3] = m.v_ll
    fr[FR_VDC] = m.vdc
    fr[FR_DA:FR_DA + 3] = m.duty_applied
    fr[FR_EN] = 1.0 if m.pwm_enabled else 0.0
    fr[FR_ENC] = m.encoder_counts
    fr[FR_SEQ] = float(m.seq)
    fr[FR_FLAGS] = float(m.status_flags & 1)  # FLAG_CLIP == STATUS_SENSOR_CLIP
    return fr


def truth_msg(store, tr: np.ndarray, seq: int, t_ns: int):
    return store.types[T_TRUTH](
        header=_stamp(store, t_ns), seq=seq, theta_e=float(tr[TR_THETA_E]),
        omega_m=float(tr[TR_WM]), torque_e=float(tr[TR_TE]), torque_load=float(tr[TR_TL]),
        i_abc_true=np.array(tr[TR_IA:TR_IA + 3], dtype=np.float64))


def truth_row(m, t_s: float) -> np.ndarray:
    tr = np.zeros(TR_N)
    tr[TR_THETA_E] = m.theta_e
    tr[TR_WM] = m.omega_m
    tr[TR_TE] = m.torque_e
    tr[TR_TL] = m.torque_load
    tr[TR_IA:TR_IA + 3] = m.i_abc_true
    tr[TR_T] = t_s
    return tr


def est_msg(store, es: np.ndarray, seq: int, t_ns: int, variant: str):
    return store.types[T_EST](
        header=_stamp(store, t_ns), seq=seq, variant=variant, theta_e=float(es[ES_TH]),
        omega_e=float(es[ES_W]), flux_ab=np.array(es[ES_LA:ES_LB + 1], dtype=np.float64),
        emf_ab=np.array(es[ES_EA:ES_EB + 1], dtype=np.float64), pll_error=float(es[ES_ERR]),
        valid=bool(es[ES_VALID] > 0.5))


def est_row(m) -> np.ndarray:
    es = np.zeros(ES_N)
    es[ES_TH] = m.theta_e
    es[ES_W] = m.omega_e
    es[ES_LA:ES_LB + 1] = m.flux_ab
    es[ES_EA:ES_EB + 1] = m.emf_ab
    es[ES_ERR] = m.pll_error
    es[ES_VALID] = 1.0 if m.valid else 0.0
    return es


def ctrl_msg(store, co: np.ndarray, seq: int, t_ns: int):
    return store.types[T_CTRL](
        header=_stamp(store, t_ns), seq=seq,
        i_dq=np.array([co[CO_ID], co[CO_IQ]]), i_dq_ref=np.array([co[CO_ID_REF], co[CO_IQ_REF]]),
        v_dq=np.array([co[CO_VD], co[CO_VQ]]), omega_ref_m=float(co[CO_W_REF]),
        omega_fb_m=float(co[CO_W_FB]), theta_used=float(co[CO_TH]), mode=int(co[CO_MODE]),
        fault_reason="" if co[CO_FAULT] == 0 else f"fault code {int(co[CO_FAULT])}")


def ctrl_row(m) -> np.ndarray:
    co = np.zeros(CO_N)
    co[CO_ID], co[CO_IQ] = m.i_dq
    co[CO_ID_REF], co[CO_IQ_REF] = m.i_dq_ref
    co[CO_VD], co[CO_VQ] = m.v_dq
    co[CO_W_REF] = m.omega_ref_m
    co[CO_W_FB] = m.omega_fb_m
    co[CO_TH] = m.theta_used
    co[CO_MODE] = m.mode
    if m.mode == MODE_FAULT:
        tail = m.fault_reason.rsplit(" ", 1)[-1]
        co[CO_FAULT] = float(tail) if tail.isdigit() else 1.0
    return co


def duty_msg(store, co: np.ndarray, seq: int, t_ns: int):
    return store.types[T_DUTY](header=_stamp(store, t_ns), seq=seq,
                               duty=np.array(co[CO_DA:CO_DA + 3], dtype=np.float64),
                               enable=bool(co[CO_EN] > 0.5))


# ------------------------------------------------------------------ writing
def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return str(x)


def run_metadata(result, k0: int = 0, obs_states: dict[str, list[float]] | None = None,
                 observers: list[str] | None = None) -> dict[str, Any]:
    sc = result.scenario
    names = result.names if observers is None else observers
    return {
        "format": 1,
        "machine": asdict(sc.machine),
        "observers": {nm: sc.observers[nm].to_dict() for nm in names
                      if nm in sc.observers},
        "driving": result.driving,
        "scenario": {"name": sc.name, "source": sc.source, "seed": sc.seed,
                     "duration_s": sc.duration_s, "steady_window_s": list(sc.steady_window_s),
                     "step_load_time_s": sc.step_load_time_s},
        "first_seq": int(k0),
        "observer_states": obs_states or {},
    }


def write_run_bag(result, path: str | Path, *, start_s: float = 0.0, end_s: float | None = None,
                  observers: list[str] | None = None, truth: bool = True, ctrl: bool = True,
                  duty: bool = True, compress: bool = False,
                  obs_states: dict[str, list[float]] | None = None,
                  extra_meta: dict[str, Any] | None = None) -> Path:
    """Write a SimResult (or a replay's arrays with the same fields) as a rosbag2/mcap bag.

    start_s/end_s cut a window out of the run; `obs_states` (observer name -> OS_* state
    at the first written frame) lets a replay of a cut bag reproduce the estimates.
    """
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    path = Path(path)
    store = typestore()
    t = result.t
    k0 = int(np.searchsorted(t, start_s - 1e-12))
    k1 = len(t) if end_s is None else int(np.searchsorted(t, end_s - 1e-12))
    names = list(result.names if observers is None else observers)
    meta = run_metadata(result, k0, obs_states, names)
    if extra_meta:
        meta.update(extra_meta)
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress:
        w.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    w.set_custom_data(META_KEY, json.dumps(meta, default=_json_default))
    with w:
        c_fr = w.add_connection(TOPIC_FRAME, T_FRAME, typestore=store)
        c_tr = w.add_connection(TOPIC_TRUTH, T_TRUTH, typestore=store) if truth else None
        c_co = w.add_connection(TOPIC_CTRL, T_CTRL, typestore=store) if ctrl else None
        c_du = w.add_connection(TOPIC_DUTY, T_DUTY, typestore=store) if duty else None
        c_es = [(result.names.index(nm), nm,
                 w.add_connection(est_topic(nm), T_EST, typestore=store)) for nm in names]
        ser = store.serialize_cdr
        for k in range(k0, k1):
            t_ns = int(round(t[k] * 1e9))
            seq = int(result.frames[k, FR_SEQ])
            w.write(c_fr, t_ns, ser(frame_msg(store, result.frames[k], t_ns), T_FRAME))
            if c_tr is not None:
                w.write(c_tr, t_ns, ser(truth_msg(store, result.truth[k], seq, t_ns), T_TRUTH))
            for i, nm, c in c_es:
                w.write(c, t_ns, ser(est_msg(store, result.est[i, k], seq, t_ns, nm), T_EST))
            if c_co is not None:
                w.write(c_co, t_ns, ser(ctrl_msg(store, result.ctrl[k], seq, t_ns), T_CTRL))
            if c_du is not None:
                w.write(c_du, t_ns, ser(duty_msg(store, result.ctrl[k], seq, t_ns), T_DUTY))
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
    return sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3")) + sorted(
        path.glob("*.zstd"))


def _info(path: Path) -> dict[str, Any]:
    import yaml

    try:
        info = yaml.safe_load((path / "metadata.yaml").read_text()) or {}
    except Exception as exc:  # noqa: BLE001
        raise BagError(f"{path}: unreadable metadata.yaml ({_one_line(exc)})") from None
    if not isinstance(info, dict) or "rosbag2_bagfile_information" not in info:
        raise BagError(f"{path}: metadata.yaml is not rosbag2 bag information")
    return info["rosbag2_bagfile_information"] or {}


def _indexed_source(path: Path):
    """rosbags AnyReader: (topics, message iterator, deserialize, close)."""
    from rosbags.highlevel import AnyReader

    reader = AnyReader([path])
    reader.open()
    topics = {c.topic: c.msgtype for c in reader.connections}
    conns = [c for c in reader.connections if _wanted(c.topic, c.msgtype)]

    def it():
        for c, t_ns, data in reader.messages(connections=conns):
            yield c.topic, c.msgtype, t_ns, data

    return topics, it(), reader.deserialize, reader.close


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
    chans: dict[int, tuple[str, str]] = {}
    topics: dict[str, str] = {}
    # read the records up front (small bags; the reader keeps no index)
    msgs: list[tuple[str, str, int, bytes]] = []
    err = None
    try:
        for rec in StreamReader(stream, emit_chunks=False).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec.name
            elif isinstance(rec, Channel):
                ty = schemas.get(rec.schema_id, "")
                chans[rec.id] = (rec.topic, ty)
                topics[rec.topic] = ty
            elif isinstance(rec, Message) and rec.channel_id in chans:
                tp, ty = chans[rec.channel_id]
                if _wanted(tp, ty):
                    msgs.append((tp, ty, rec.log_time, rec.data))
    except Exception as exc:  # noqa: BLE001
        err = exc
    store = typestore()

    def it():
        yield from msgs
        if err is not None:
            raise EOFError(f"data ends after {len(msgs)} readable messages "
                           f"({_one_line(err)})")

    return topics, it(), store.deserialize_cdr, lambda: None


def _wanted(topic: str, msgtype: str) -> bool:
    return ((topic == TOPIC_FRAME and msgtype == T_FRAME)
            or (topic == TOPIC_TRUTH and msgtype == T_TRUTH)
            or (topic == TOPIC_CTRL and msgtype == T_CTRL)
            or (topic.startswith(EST_PREFIX) and topic.endswith(EST_SUFFIX)
                and msgtype == T_EST))


def read_run_bag(path: str | Path, keep_raw: bool = False) -> RunBag:
    """Read a drive bag into aligned arrays.  Raises BagError (one line) for a bag that
    holds nothing replayable; a damaged or partial bag returns what it holds, with the
    damage listed in `problems`."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    if path.is_file():  # a bare .mcap file: use its folder if that is a bag
        if (path.parent / "metadata.yaml").exists():
            path = path.parent
        else:
            raise BagError(f"{path}: not a rosbag2 folder (no metadata.yaml next to it)")
    if not (path / "metadata.yaml").exists():
        raise BagError(f"{path}: not a rosbag2 bag (no metadata.yaml)")
    info = _info(path)
    if not _bag_files(path):
        raise BagError(f"{path}: bag has no storage file (.mcap/.db3)")
    problems: list[str] = []
    meta: dict[str, Any] = {}
    try:
        cd = info.get("custom_data") or {}
        if META_KEY in cd:
            meta = json.loads(cd[META_KEY])
    except Exception:  # noqa: BLE001
        problems.append("unreadable fluxdrive metadata (ignored)")
    expected: dict[str, int] = {}
    for tm in info.get("topics_with_message_count") or []:
        try:
            md = tm["topic_metadata"]
            if _wanted(md["name"], md["type"]):
                expected[md["name"]] = int(tm["message_count"])
        except (KeyError, TypeError, ValueError):
            pass
    try:
        topics, messages, deser, close = _indexed_source(path)
    except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds; name the problem
        first = f"{type(exc).__name__}: {_one_line(exc)}"
        try:
            topics, messages, deser, close = _stream_source(path)
        except BagError:
            raise
        except Exception:  # noqa: BLE001
            raise BagError(f"{path}: cannot open bag ({first}); not a readable rosbag2 "
                           f"bag") from None
        if not topics:
            raise BagError(f"{path}: cannot open bag ({first}); storage holds no readable "
                           f"records (truncated or damaged)") from None
        problems.append(f"bag index unreadable ({first}): storage truncated, read "
                        f"sequentially")
    counts: dict[str, int] = {}
    fr_rows: dict[int, np.ndarray] = {}
    fr_t: dict[int, int] = {}
    raw: list[tuple[int, bytes]] = []
    tr_rows: dict[int, np.ndarray] = {}
    co_rows: dict[int, np.ndarray] = {}
    es_rows: dict[str, dict[int, np.ndarray]] = {}
    try:
        if not topics:
            raise BagError(f"{path}: bag is empty (no topics)")
        if TOPIC_FRAME not in topics:
            ours = [tp for tp, ty in topics.items() if ty.startswith("flux_drive_msgs/")]
            if not ours:
                raise BagError(f"{path}: no fluxdrive topics; bag holds foreign message types "
                               f"{sorted(set(topics.values()))[:4]}")
            raise BagError(f"{path}: no {TOPIC_FRAME} topic (bag has {sorted(topics)})")
        if topics[TOPIC_FRAME] != T_FRAME:
            raise BagError(f"{path}: {TOPIC_FRAME} has type {topics[TOPIC_FRAME]}, "
                           f"expected {T_FRAME}")
        try:
            for tp, msgtype, t_ns, data in messages:
                counts[tp] = counts.get(tp, 0) + 1
                try:
                    m = deser(data, msgtype)
                except Exception as exc:  # noqa: BLE001
                    problems.append(f"undecodable {tp} message ({_one_line(exc)})")
                    continue
                if tp == TOPIC_FRAME:
                    fr_rows[m.seq] = frame_row(m)
                    st = m.header.stamp
                    fr_t[m.seq] = st.sec * 1_000_000_000 + st.nanosec
                    if keep_raw:
                        raw.append((t_ns, bytes(data)))
                elif tp == TOPIC_TRUTH:
                    tr_rows[m.seq] = truth_row(m, 0.0)
                elif tp == TOPIC_CTRL:
                    co_rows[m.seq] = ctrl_row(m)
                else:
                    es_rows.setdefault(tp[len(EST_PREFIX):-len(EST_SUFFIX)], {})[m.seq] = \
                        est_row(m)
        except Exception as exc:  # noqa: BLE001
            got = sum(counts.values())
            problems.append(f"bag truncated or damaged after {got} messages "
                            f"({type(exc).__name__}: {_one_line(exc)})")
    finally:
        try:
            close()
        except Exception:  # noqa: BLE001
            pass
    if not fr_rows:
        raise BagError(f"{path}: no readable {TOPIC_FRAME} messages "
                       + (f"({problems[-1]})" if problems else "(topic is empty)"))
    seqs = np.array(sorted(fr_rows), dtype=np.int64)
    n = len(seqs)
    frames = np.array([fr_rows[s] for s in seqs])
    t = np.array([fr_t[s] for s in seqs], dtype=np.float64) * 1e-9
    span = int(seqs[-1] - seqs[0] + 1)
    if span > n:
        problems.append(f"{span - n} of {span} frames missing (seq gaps); replaying the "
                        f"{n} present back to back")
    for tp, want in expected.items():
        got = counts.get(tp, 0)
        if want > got:
            problems.append(f"{tp}: {got} of {want} messages read ({want - got} missing)")

    def align(rows: dict[int, np.ndarray], width: int, tp: str) -> np.ndarray | None:
        if not rows:
            return None
        out = np.full((n, width), np.nan)
        hit = 0
        for j, s in enumerate(seqs):
            r = rows.get(int(s))
            if r is not None:
                out[j] = r
                hit += 1
        if hit < n:
            problems.append(f"{tp}: {n - hit} of {n} frames have no matching message")
        return out

    truth = align(tr_rows, TR_N, TOPIC_TRUTH)
    if truth is not None:
        truth[:, TR_T] = t
    ctrl = align(co_rows, CO_N, TOPIC_CTRL)
    est = {nm: align(rows, ES_N, est_topic(nm)) for nm, rows in es_rows.items()}
    return RunBag(path, t, frames, truth, est, ctrl, meta, counts, problems, raw)


def _one_line(exc: BaseException) -> str:
    s = str(exc).strip().splitlines()
    return (s[0] if s else type(exc).__name__)[:200]


__all__ = ["BagError", "RunBag", "read_run_bag", "write_run_bag", "typestore", "est_topic",
           "TOPIC_FRAME", "TOPIC_TRUTH", "TOPIC_DUTY", "TOPIC_CTRL"]


def observer_states_at(result, k0: int) -> dict[str, list[float]]:
    """The recorded observers' OS_* states just before frame k0, by re-running each over
    frames 0..k0-1 (the same compiled kernel as the run, so the same numbers): stored in a
    cut-out bag so that replaying it continues the live estimates exactly."""
    from fluxdrive.drive.observers import KernelObserver

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
