"""Raw-sample export of the scope's view: the full-rate samples it holds, as CSV and as a
bag (one MCAP file) written with the project's one bag writer.

CSV: a header `t_s,seq,<stream:field>...`, then one row per sample in sample order; every
value in Python's shortest round-trip form (`repr`), so the file holds the float64 the
scope decoded from the graph's messages bit for bit; a field a stream has no sample for
at that seq is empty.

Bag: per stream a topic `/scope/raw/<stream>` of `std_msgs/msg/Float64MultiArray` (a
standard type every ROS and MCAP tool decodes), one message per sample: `data` is
[seq, field values...] and `layout.dim[0].label` names them ("seq,i_a,i_b,..."); the log
time is the sample time seq·ts (plus the writer's epoch offset, recorded in the metadata).
The metadata `scope_export` says the view (t0, t1), the streams and their fields.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

RAW_TOPIC = "/scope/raw/"
T_ARRAY = "std_msgs/msg/Float64MultiArray"

Streams = dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]


def raw_csv(streams: Streams, ts_s: float) -> str:
    """The samples of `streams` (name -> (seq, {field: values})) as CSV text."""
    cols: list[tuple[str, dict[int, float]]] = []
    seqs: set[int] = set()
    for name, (seq, fields) in streams.items():
        s = [int(v) for v in np.asarray(seq).tolist()]
        seqs.update(s)
        for f, v in fields.items():
            cols.append((f"{name}:{f}", dict(zip(s, np.asarray(v, float).tolist(), strict=True))))
    out = io.StringIO()
    out.write(",".join(["t_s", "seq", *(c[0] for c in cols)]) + "\n")
    for k in sorted(seqs):
        cells = [repr(k * ts_s), str(k)]
        for _, m in cols:
            got = m.get(k)
            cells.append("" if got is None else repr(got))
        out.write(",".join(cells) + "\n")
    return out.getvalue()


def read_raw_csv(text: str) -> tuple[list[str], np.ndarray]:
    """Header and values (NaN where empty) of a raw CSV: the inverse of raw_csv."""
    lines = text.splitlines()
    head = lines[0].split(",")
    rows = [[float(c) if c else np.nan for c in ln.split(",")] for ln in lines[1:] if ln]
    return head, np.array(rows, dtype=float).reshape(len(rows), len(head))


def write_raw_bag(path: str | Path, streams: Streams, ts_s: float, info: dict[str, Any]) -> Path:
    """The samples of `streams` as a bag at `path` (a new rosbag2 folder); returns its MCAP
    file."""
    from fluxdrive.io.bagio import BagWriter, typestore

    store = typestore()
    arr_cls = store.types[T_ARRAY]
    layout_cls = store.types["std_msgs/msg/MultiArrayLayout"]
    dim_cls = store.types["std_msgs/msg/MultiArrayDimension"]
    meta = {
        **info,
        "streams": {n: ["seq", *f] for n, (_s, f) in streams.items()},
    }
    with BagWriter(path, {"scope_export": meta, "ts_s": ts_s}) as w:
        for name, (seq, fields) in streams.items():
            if not len(seq):
                continue
            label = ",".join(["seq", *fields])
            nf = len(fields) + 1
            layout = layout_cls(dim=[dim_cls(label=label, size=nf, stride=nf)], data_offset=0)
            rows = np.column_stack([np.asarray(seq, float), *(fields[f] for f in fields)])
            cid = w.add_connection(RAW_TOPIC + name, T_ARRAY)
            for k, row in zip(np.asarray(seq).tolist(), rows, strict=True):
                msg = arr_cls(layout=layout, data=np.ascontiguousarray(row, dtype=np.float64))
                w.write(cid, int(round(int(k) * ts_s * 1e9)), store.serialize_cdr(msg, T_ARRAY))
    return next(Path(path).glob("*.mcap"))


def read_raw_bag(path: str | Path) -> Streams:
    """The streams of an exported bag, read with the project's bag reader (read_raw)."""
    from fluxdrive.io.bagio import read_raw, typestore

    store = typestore()
    got: dict[str, tuple[list[str], list[np.ndarray]]] = {}
    for topic, mtype, _t, raw in read_raw(path, lambda t: t.startswith(RAW_TOPIC)):
        m = store.deserialize_cdr(bytes(raw), mtype)
        entry = got.setdefault(topic[len(RAW_TOPIC) :], (m.layout.dim[0].label.split(","), []))
        entry[1].append(np.asarray(m.data, float))
    out: Streams = {}
    for name, (labels, rows) in got.items():
        a = np.array(rows).reshape(len(rows), len(labels))
        out[name] = (a[:, 0].astype(np.int64), {f: a[:, i + 1] for i, f in enumerate(labels[1:])})
    return out
