"""rosbag2 I/O of the project: the typestore (project types registered from their .msg text,
so every bag embeds its message definitions), and reading a run's bag back into the
engine's arrays (what fluxdrive.metrics consumes, same layout as fluxdrive.sim.SimResult).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from fluxdrive_ros.cdr import Decoder, msg_dir

from fluxdrive_ros import topics

_STORE = None


def typestore():
    """rosbags typestore: ROS 2 Jazzy's standard types + every flux_drive_msgs message."""
    global _STORE
    if _STORE is None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        store = get_typestore(Stores.ROS2_JAZZY)
        types = {}
        for p in sorted(msg_dir().glob("*.msg")):
            types.update(get_types_from_msg(p.read_text(), f"flux_drive_msgs/msg/{p.stem}"))
        store.register(types)
        _STORE = store
    return _STORE


def bag_files(bag: Path) -> list[Path]:
    return sorted(Path(bag).glob("*.mcap"))


def read_raw(bag: Path, topic_filter=None):
    """Yield (topic, msgtype, timestamp_ns, rawdata) in log order, with rosbags' AnyReader."""
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
        conns = [c for c in reader.connections if topic_filter is None or topic_filter(c.topic)]
        for conn, ts, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, ts, raw


def topic_counts(bag: Path) -> dict[str, int]:
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
        out: dict[str, int] = {}
        for c in reader.connections:
            out[c.topic] = out.get(c.topic, 0) + c.msgcount
        return out


_EST_RE = re.compile(r"^/obs/([^/]+)/estimate$")


def load_run_arrays(bag: Path, ts_s: float, names: list[str] | None = None):
    """A run's bag -> dict of engine arrays indexed by seq:
    frames (N, FR_N), truth (N, TR_N), est (n_obs, N, ES_N), ctrl (N, CO_N), names, seqs.
    N = last frame seq + 1; rows of samples missing from the bag stay NaN (and `missing`
    counts them per topic)."""
    from fluxdrive.control import CO_N
    from fluxdrive.observers import ES_N
    from fluxdrive.plant import FR_N, TR_N
    from fluxdrive_ros.wire import control_row, estimate_row, fault_code, frame_row, truth_row

    decs: dict[str, Decoder] = {}  # one per topic: each keeps its strings' layout
    frames: dict[int, np.ndarray] = {}
    truth: dict[int, np.ndarray] = {}
    est: dict[str, dict[int, np.ndarray]] = {}
    duty: dict[int, tuple] = {}
    state: dict[int, tuple] = {}
    faults: dict[int, int] = {}
    for topic, mtype, _, raw in read_raw(bag):
        d = decs.get(topic)
        if d is None:
            d = decs[topic] = Decoder(mtype)
        if topic == topics.FRAME and mtype == topics.T_FRAME:
            v = d.decode(raw)
            frames[v[2]] = frame_row(v)
        elif topic == topics.TRUTH and mtype == topics.T_TRUTH:
            v = d.decode(raw)
            truth[v[2]] = truth_row(v, ts_s)
        elif mtype == topics.T_ESTIMATE:
            m = _EST_RE.match(topic)
            name = m.group(1) if m else topic
            v = d.decode(raw)
            est.setdefault(name, {})[v[2]] = estimate_row(v)
        elif topic == topics.DUTY and mtype == topics.T_DUTY:
            v = d.decode(raw)
            duty[v[2]] = v
        elif topic == topics.CONTROLLER_STATE and mtype == topics.T_STATE:
            v = d.decode(raw)
            state[v[2]] = v
            reason = d.codec_for(raw).strings.get("fault_reason", "")
            if reason:
                faults[v[2]] = fault_code(reason)
    n = (max(frames) + 1) if frames else 0
    names = list(names) if names is not None else sorted(est)

    def stack(d: dict[int, np.ndarray], width: int) -> np.ndarray:
        out = np.full((n, width), np.nan)
        for k, row in d.items():
            if 0 <= k < n:
                out[k] = row
        return out

    ctrl = {k: control_row(duty.get(k), state.get(k), faults.get(k, 0))
            for k in set(duty) | set(state)}
    res = {
        "n": n,
        "frames": stack(frames, FR_N),
        "truth": stack(truth, TR_N),
        "est": np.stack([stack(est.get(nm, {}), ES_N) for nm in names]) if names
        else np.zeros((0, n, ES_N)),
        "ctrl": stack(ctrl, CO_N),
        "names": names,
        "missing": {
            "frame": n - len(frames), "truth": n - len(truth),
            **{f"estimate/{nm}": n - len(est.get(nm, {})) for nm in names},
            "duty": n - len(duty), "controller_state": n - len(state),
        },
    }
    return res
