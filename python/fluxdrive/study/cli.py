"""`./fluxdrive study SPEC.yaml --out DIR [--scheduler tcp://HOST:PORT] [--workers N]`:
sweeps and Monte-Carlo robustness maps (see docs/study.md).

Runs every task of the spec (variants x grid x draws) on a dask LocalCluster using every core,
on an existing cluster (--scheduler), or in-process (--workers 1); rows stream into
DIR/parts/*.parquet as tasks finish and are compacted into DIR/results.parquet at the end.
Run it again with the same --out to resume: finished tasks are skipped (also after adding
draws, grid points or variants to the spec: only the new tasks run).  Then the maps:
DIR/p_stable.png, DIR/theta_rms.png, DIR/report.md, DIR/summary.json.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from fluxdrive.core.machine import ConfigError
from fluxdrive.core.schema import Parser
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive.study import maps, store
from fluxdrive.study.runner import Progress, Runner
from fluxdrive.study.spec import StudySpec, load_spec
from fluxdrive.study.tasks import run_task, warm_kernels


def run_study(
    spec: StudySpec,
    out: Path,
    runner: Runner,
    restart: bool = False,
    echo: bool = True,
    on_result=None,
    flush_s: float = 10.0,
) -> dict[str, Any]:
    """Run (or resume) a study into `out`; returns a summary (tasks, skipped, failures,
    lowest speeds).  `on_result(outcome)` is called after each finished task."""

    out = Path(out)
    if restart and out.exists():
        for p in ("parts", "results.parquet", "failures.jsonl"):
            q = out / p
            shutil.rmtree(q) if q.is_dir() else q.unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    tasks = spec.tasks()
    done = _finished_tasks(out, tasks)
    todo = [t for t in tasks if t["task_id"] not in done]
    if echo:
        print(
            f"study {spec.name}: {len(tasks)} tasks ({len(spec.variants)} variants x "
            f"{len(tasks) // max(1, len(spec.variants) * spec.draws)} grid points x "
            f"{spec.draws} draws), {len(tasks) - len(todo)} already done, {len(todo)} to run "
            f"on {_describe(runner)}",
            file=sys.stderr,
            flush=True,
        )
    t0 = time.perf_counter()
    failures = _run_tasks(spec, out, runner, todo, echo, on_result, flush_s)
    elapsed = time.perf_counter() - t0
    table = store.compact(out, [t["task_id"] for t in tasks])
    info = {
        "tasks": len(tasks),
        "runner": _describe(runner),
        "elapsed_s": elapsed,
        "commit": _commit(),
    }
    rep = (
        maps.write_report(table, spec, out, failures, info)
        if table is not None
        else {"lowest": {}, "figures": []}
    )
    summary = {
        "study": spec.name,
        "tasks": len(tasks),
        "ran": len(todo),
        "skipped": len(tasks) - len(todo),
        "rows": 0 if table is None else table.num_rows,
        "failed": len(failures),
        "elapsed_s": round(elapsed, 2),
        "runner": _describe(runner),
        "commit": info["commit"],
        "cpu_s": None
        if table is None
        else round(sum(x for x in table.column("cpu_s").to_pylist() if x is not None), 1),
        "lowest_speed": rep["lowest"],
        "figures": rep["figures"],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def _finished_tasks(out: Path, tasks: list[dict[str, Any]]) -> dict[str, str]:
    """task_id -> input hash of the tasks `out` already holds; refused when one of them was
    computed from other inputs than the spec's today (or without hashes)."""

    old_t = store.read_table(out)
    if old_t is None:
        return {}
    if "input_hash" not in old_t.column_names:
        raise ConfigError(
            f"{out} holds a table without input hashes; use another --out, "
            f"or --restart to discard it"
        )
    done = dict(
        zip(
            old_t.column("task_id").to_pylist(),
            old_t.column("input_hash").to_pylist(),
            strict=True,
        )
    )
    changed = [
        t["task_id"]
        for t in tasks
        if t["task_id"] in done and done[t["task_id"]] != t["input_hash"]
    ]
    if changed:
        raise ConfigError(
            f"{out} holds results of {len(changed)} task(s) computed from other "
            f"inputs (the spec changed, e.g. {changed[0]}); use another --out, or "
            f"--restart to discard them"
        )
    return done


# what a failed task's record repeats of its inputs
_FAILURE_INPUTS = ("variant", "variant_cfg", "grid", "draw", "seed", "random", "scenario")


def _run_tasks(
    spec: StudySpec,
    out: Path,
    runner: Runner,
    todo: list[dict[str, Any]],
    echo: bool,
    on_result,
    flush_s: float,
) -> list[dict[str, Any]]:
    """Run `todo` on the runner, rows streamed into out/parts as tasks finish; returns the
    failures (also written to out/failures.jsonl, whatever happens)."""

    schema = store.schema_for(list(spec.grid), spec.random_columns())
    w = store.TableWriter(out, schema, flush_s=flush_s)
    failures: list[dict[str, Any]] = []
    prog = Progress(len(todo), label=f"study {spec.name}", echo=echo)
    try:
        for o in runner.run_unordered(run_task, ((t["task_id"], t) for t in todo), prog):
            if o.ok:
                w.add(store.flat_row(o.payload, o.value, o.attempts, o.worker))
            else:
                failures.append(
                    {
                        "task_id": o.key,
                        "attempts": o.attempts,
                        "error": o.error,
                        "inputs": {k: o.payload[k] for k in _FAILURE_INPUTS},
                    }
                )
                if echo:
                    print(
                        f"[study] task {o.key} FAILED after {o.attempts} attempts: "
                        f"{o.error.splitlines()[0] if o.error else '?'}",
                        file=sys.stderr,
                    )
            if on_result is not None:
                on_result(o)
    finally:
        w.close()
        store.write_failures(out, failures)
    return failures


def _noop(x: Any) -> Any:
    return x


def _commit() -> str:
    """The fluxdrive commit the study ran on (+ '-dirty' with uncommitted engine changes)."""
    import subprocess

    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short=10", "HEAD"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "python", "config"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (head or "unknown") + ("-dirty" if dirty else "")


def _describe(r: Runner) -> str:
    if r.client is None:
        return "in-process (serial)"
    kind = "LocalCluster" if r.cluster is not None else "cluster"
    return f"{kind} {r.address} ({r.workers} workers)"


def bench_study(argv: list[str]) -> dict[str, Any]:
    """tasks/s of 1 s simulated runs on 1 and 2 local workers, speed-up, and the scheduling
    overhead per task (wall per task on one worker minus the task's own wall)."""
    import tempfile

    import yaml

    ap = Parser(prog="fluxdrive benchmark study")
    ap.add_argument(
        "--tasks",
        type=int,
        default=60,
        help="tasks per worker count (fewer: fixed start-up costs dominate)",
    )
    ap.add_argument("--duration-s", type=float, default=1.0)
    args = ap.parse_args(argv)
    warm_kernels()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="fluxdrive-bench-study-") as d:
        sp = Path(d) / "bench.yaml"
        sp.write_text(yaml.safe_dump(_bench_spec(args.tasks, args.duration_s)))
        tasks = load_spec(sp).tasks()
        res = {n: _time_workers(tasks, n, args.duration_s) for n in (1, 2)}
    load_after = os.getloadavg()
    ov = res[1]["overhead_s"]
    noop_s = res[1]["noop_s"]
    return {
        "tasks_per_s_1": round(res[1]["tasks_per_s"], 3),
        "tasks_per_s_2": round(res[2]["tasks_per_s"], 3),
        "speedup": round(res[2]["tasks_per_s"] / res[1]["tasks_per_s"], 3),
        "goal_speedup": 1.8,
        "overhead_ms_per_task": round(ov * 1e3, 2),
        "overhead_pct_of_1s_run": round(100 * ov / res[1]["task_wall_s"], 2),
        # load-independent-ish: an empty task's round trip against the run's CPU time
        # (= its wall time on an idle core)
        "empty_task_ms": round(noop_s * 1e3, 2),
        "empty_task_pct_of_1s_run_cpu": round(100 * noop_s / res[1]["task_cpu_s"], 2),
        "goal_overhead_pct": 5.0,
        "task_wall_s": round(res[1]["task_wall_s"], 3),
        "task_cpu_s": round(res[1]["task_cpu_s"], 3),
        "core_share_1_2": [round(res[1]["core_share"], 2), round(res[2]["core_share"], 2)],
        "tasks": args.tasks,
        "cores": os.cpu_count(),
        "loadavg_1min_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
    }


def _bench_spec(draws: int, duration_s: float) -> dict[str, Any]:
    """The benchmark's study: `draws` runs of the paper scenario, R^ drawn at random."""
    return {
        "name": "bench",
        "seed": 7,
        "draws": draws,
        "scenario": {
            "file": "paper_2pct_150load",
            "params": {"duration_s": duration_s, "steady_window_s": [0.5 * duration_s, duration_s]},
        },
        "variants": {"flux_measured": {"variant": "paper", "voltage_source": "measured"}},
        "random": {"r_hat_err": {"dist": "uniform", "low": -0.1, "high": 0.1}},
    }


def _time_workers(tasks: list[dict[str, Any]], n: int, duration_s: float) -> dict[str, float]:
    """The tasks run on a LocalCluster of `n` warmed workers: rate, per-task wall and CPU,
    the workers' core share, the overhead per task and (one worker) an empty task's cost."""
    with Runner("local", workers=n) as r:
        assert r.client is not None  # "local": a LocalCluster's client
        # warm every worker (imports, kernel cache) before timing
        r.client.run(warm_kernels)
        t0 = time.perf_counter()
        walls, cpus = [], []
        for o in r.run_unordered(run_task, ((t["task_id"], t) for t in tasks)):
            if not o.ok:
                raise RuntimeError(o.error)
            walls.append(o.value["wall_s"])
            cpus.append(o.value["cpu_s"])
        el = time.perf_counter() - t0
        noop_s = float("nan")
        if n == 1:  # the runner's own cost: empty tasks, submit to result
            t1 = time.perf_counter()
            r.map(_noop, list(range(40)))
            noop_s = (time.perf_counter() - t1) / 40
    rate = len(tasks) / el
    task_s = sum(walls) / len(walls)
    task_cpu_s = sum(cpus) / len(cpus)
    # the workers' share of a core while they ran: 1.0 on an idle machine; below it,
    # other processes took the rest (then speed-up figures measure the machine's load)
    share = sum(cpus) / (el * n)
    overhead_s = el * n / len(tasks) - task_s
    print(
        f"[bench] {n} worker(s): {len(tasks)} tasks of {duration_s:g} s "
        f"simulated in {el:.2f} s = {rate:.2f} tasks/s (task itself {task_s:.3f} s "
        f"wall, {task_cpu_s:.3f} s CPU; workers got {share:.0%} of a core "
        f"each; overhead {overhead_s * 1e3:.1f} ms/task)",
        file=sys.stderr,
    )
    return {
        "tasks_per_s": rate,
        "task_wall_s": task_s,
        "elapsed_s": el,
        "task_cpu_s": task_cpu_s,
        "core_share": share,
        "overhead_s": overhead_s,
        "noop_s": noop_s,
    }
