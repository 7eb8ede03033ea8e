"""The study table: one Parquet table per study folder, written as tasks finish.

    DIR/results.parquet     the compacted table (written when a study completes)
    DIR/parts/*.parquet     rows streamed while it runs (a part file every 10 s at most,
                            written to a temporary name and renamed, so an interrupted
                            study leaves only whole files behind)
    DIR/failures.jsonl      tasks that failed twice: their inputs and the error

`read_table(DIR)` is both, deduplicated by task_id; a resumed (or extended: more draws, grid
points, variants) study skips the tasks whose id and input hash are there.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from fluxdrive.study.tasks import OUTPUTS

RUN_COLUMNS = ["attempts", "worker"]  # how it ran, not what it computed
TIMING_COLUMNS = ["wall_s", "cpu_s"]


def schema_for(grid_axes: list[str], random_cols: list[str]) -> pa.Schema:
    f = [
        pa.field("task_id", pa.string()),
        pa.field("input_hash", pa.string()),
        pa.field("variant", pa.string()),
    ]
    f += [pa.field(a, pa.float64()) for a in grid_axes]
    f += [pa.field("draw", pa.int64()), pa.field("seed", pa.int64())]
    f += [pa.field(c, pa.float64()) for c in random_cols]
    f += [pa.field(k, getattr(pa, t)()) for k, t in OUTPUTS.items()]
    f += [pa.field("attempts", pa.int64()), pa.field("worker", pa.string())]
    return pa.schema(f)


def flat_row(
    payload: dict[str, Any], value: dict[str, Any], attempts: int, worker: str
) -> dict[str, Any]:
    row: dict[str, Any] = {
        "task_id": payload["task_id"],
        "input_hash": payload["input_hash"],
        "variant": payload["variant"],
        "draw": payload["draw"],
        "seed": payload["seed"],
    }
    row.update(payload["grid"])
    for k, v in payload["random"].items():
        if isinstance(v, list):
            row.update({f"{k}_{p}": x for p, x in zip("abc", v, strict=True)})
        else:
            row[k] = v
    row.update({k: value.get(k) for k in OUTPUTS})
    row["attempts"], row["worker"] = attempts, worker
    return row


class TableWriter:
    """Buffers rows and writes a part file every `flush_s` seconds (and on close)."""

    def __init__(self, out: Path, schema: pa.Schema, flush_s: float = 10.0):
        self.dir = Path(out) / "parts"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.schema = schema
        self.flush_s = flush_s
        self.rows: list[dict[str, Any]] = []
        self.last = time.monotonic()
        self.n_parts = len(list(self.dir.glob("part-*.parquet")))

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        if time.monotonic() - self.last >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        self.last = time.monotonic()
        if not self.rows:
            return
        t = pa.Table.from_pylist(self.rows, schema=self.schema)
        while (p := self.dir / f"part-{self.n_parts:05d}.parquet").exists():
            self.n_parts += 1
        tmp = p.with_suffix(".tmp")
        pq.write_table(t, tmp)
        os.replace(tmp, p)
        self.n_parts += 1
        self.rows = []

    def close(self) -> None:
        self.flush()


def read_table(out: Path) -> pa.Table | None:
    """Every row written so far (compacted table + parts), one row per task_id."""
    out = Path(out)
    tabs = []
    if (out / "results.parquet").exists():
        tabs.append(pq.read_table(out / "results.parquet"))
    for p in sorted((out / "parts").glob("part-*.parquet")) if (out / "parts").exists() else []:
        tabs.append(pq.read_table(p))
    if not tabs:
        return None
    t = pa.concat_tables(tabs, promote_options="default")
    ids = t.column("task_id").to_pylist()
    seen: set[str] = set()
    keep = []
    for i, tid in enumerate(ids):
        if tid not in seen:
            seen.add(tid)
            keep.append(i)
    return t.take(keep) if len(keep) != len(ids) else t


def compact(out: Path, order: list[str]) -> pa.Table | None:
    """Write results.parquet (rows in the spec's task order) and drop the parts."""
    t = read_table(out)
    if t is None:
        return None
    pos = {tid: i for i, tid in enumerate(order)}
    ids = t.column("task_id").to_pylist()
    idx = sorted(range(len(ids)), key=lambda i: pos.get(ids[i], len(order) + i))
    t = t.take(idx)
    tmp = Path(out) / "results.parquet.tmp"
    pq.write_table(t, tmp)
    os.replace(tmp, Path(out) / "results.parquet")
    for p in (Path(out) / "parts").glob("part-*.parquet"):
        p.unlink()
    return t


def write_failures(out: Path, failures: list[dict[str, Any]]) -> None:
    path = Path(out) / "failures.jsonl"
    if not failures:
        path.unlink(missing_ok=True)
        return
    path.write_text("".join(json.dumps(f, default=str) + "\n" for f in failures))
