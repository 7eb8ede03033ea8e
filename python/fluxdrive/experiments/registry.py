"""`./fluxdrive experiment NAME|all [--quick] [--graph] [--out DIR]`: the paper's figures, and
past them.  `--graph` runs every scenario through the ROS node graph instead of in-process.

Each experiment builds scenarios, runs them through the project's one parallel runner
(fluxdrive.study.runner: a dask LocalCluster on every core, an existing cluster with
--scheduler, or in-process with --workers 1), writes
PNGs laid out like the paper's figure, and one row per claim of the paper into
report.md / report.json: {"claim", "ours", "holds", "why"}.  "why" explains every claim
that does not hold with our numbers (physics first; nothing is tuned silently).

Experiments live in experiments_paper.py (Figs. 2-4, 13-19) and experiments_beyond.py
(lowest speed, mismatch, sensitivity, online R_s, speed reversal, where peers fail).
Each one is `fn(ctx) -> dict` with keys claims, figures, data; `ctx.run(jobs)` runs
(scenario, extractor) jobs and returns the extractors' outputs, so only small arrays cross
process boundaries.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.scenario import (
    REPO_ROOT,
    machine_path,
)
from fluxdrive.experiments import common
from fluxdrive.experiments.claims import VERDICT_TEXT, count, counts_line

# re-exported: study specs, the graph runner and tests name them here
from fluxdrive.experiments.common import (  # noqa: F401
    DEFAULT_MACHINE,
    LITERAL,
    OBS4,
    OBS6,
    CardValues,
    Ctx,
    build,
    claim,
    cv,
    encoder_run,
    plt,
    sensorless,
    use_graph_runner,
)


# ---------------------------------------------------------------- registry
def _registry() -> dict[str, tuple[Callable, str]]:
    from fluxdrive.experiments import beyond as b
    from fluxdrive.experiments import fronts as f
    from fluxdrive.experiments import paper as p

    return {**p.EXPERIMENTS, **f.EXPERIMENTS, **b.EXPERIMENTS}


def run_experiment(
    name: str, out: Path, quick: bool = False, runner=None, echo: bool = True
) -> dict:
    fn, title = _registry()[name]
    ctx = Ctx(out=Path(out), quick=quick, runner=runner, name=name, echo=echo)
    t0 = time.perf_counter()
    res = fn(ctx)
    res["runtime_s"] = round(time.perf_counter() - t0, 2)
    res["title"] = title
    res["quick"] = quick
    return res


def _fmt_holds(h) -> str:
    return {True: "yes", False: "**no**", None: "n/a"}[h]


def _fmt_verdict(c: dict) -> str:
    """A registered claim's verdict (bold where a reproduction fails); a claim beyond the
    paper (no verdict): whether it holds."""
    v = c.get("verdict")
    if v is None:
        return _fmt_holds(c["holds"])
    text = VERDICT_TEXT[v]
    if v in ("disagreement", "modelling_gap"):
        return f"**{text}**"
    # a calibrated or by-design claim never counts as held, but one that fails its own
    # registered test says so
    return text if c.get("passes", True) else f"{text} (**fails its test**)"


def _claim_rows(claims: list[dict]) -> list[str]:
    lines = [
        "| id | claim (source; operating point) | class | registered test | ours | verdict "
        "| why / note |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in claims:
        why = c.get("why", c.get("note", ""))
        if "verdict" in c:
            what = f"{_md(c['claim'])} ({_md(c['source'])}; {_md(c['operating_point'])})"
            test = f"{_md(c['test'])}: **{c['value']:.4g}**"
            cls = c["class"].replace("_", " ")
        else:
            what, test, cls = _md(c["claim"]), "", "beyond the paper"
        lines.append(
            f"| {c.get('id', '')} | {what} | {cls} | {test} | {_md(c['ours'])} | "
            f"{_fmt_verdict(c)} | {_md(why)} |"
        )
    return lines


def write_report(out: Path, results: dict[str, dict]) -> None:
    """Merge into out/report.json and regenerate out/report.md."""
    out.mkdir(parents=True, exist_ok=True)
    jpath = out / "report.json"
    allres: dict[str, Any] = {}
    if jpath.exists():
        try:
            allres = json.loads(jpath.read_text()).get("experiments", {})
        except (ValueError, OSError):
            allres = {}
    allres.update(results)
    order = list(_registry())
    allres = {
        k: allres[k] for k in sorted(allres, key=lambda k: order.index(k) if k in order else 999)
    }
    jpath.write_text(json.dumps({"experiments": allres}, indent=1, default=_json_default))
    n = count([c for r in allres.values() for c in r.get("claims", [])])
    lines = [
        "# fluxdrive experiments: the paper's claims with our numbers",
        "",
        "Chen, Chen, Yang, IEEE Access 2019, reproduced on the switching-level engine "
        "(docs/engine.md).  Every claim of the paper is registered before the runs in "
        "config/claims.yaml: its source, operating point, the quantity measured, the test and "
        "threshold, and a class.  The verdict comes from that table: only a reproduction that "
        "passes is *held*; a failing one is a genuine disagreement or a modelling gap (why: "
        "the mechanism); a claim a model number was fitted to (*calibrated*) or a setting was "
        "chosen for (*by design*) shows its number but is not counted.  THD is orders 2..20, "
        "THD+N everything but the fundamental; rows that use either show both.",
        "",
        f"**Claims: {counts_line(n)}.**",
        "",
    ]
    for name, r in allres.items():
        lines += [
            f"## {name}: {r.get('title', '')}",
            "",
            f"runtime {r.get('runtime_s', 0):.1f} s{' (quick)' if r.get('quick') else ''}",
            "",
        ]
        lines += _claim_rows(r.get("claims", []))
        lines.append("")
        for f in r.get("figures", []):
            lines.append(f"![{f}]({f})")
        lines.append("")
    (out / "report.md").write_text("\n".join(lines))


def _md(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, float) and math.isnan(o):
        return None
    return str(o)


def main(argv: list[str]) -> int:
    reg = _registry()
    ap = argparse.ArgumentParser(
        prog="fluxdrive experiment",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("name", help="experiment name or 'all' or 'list': " + ", ".join(reg))
    ap.add_argument("--quick", action="store_true", help="fewer points, shorter runs")
    ap.add_argument("--out", type=Path, help="output folder (default results/experiments)")
    ap.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="worker processes of the local dask cluster (1: in-process)",
    )
    ap.add_argument("--scheduler", help="run on an existing dask cluster tcp://HOST:PORT")
    ap.add_argument(
        "--graph",
        action="store_true",
        help="run every scenario through the ROS 2 node graph (lockstep, "
        "recorded to a bag and read back) instead of in-process; same numbers, "
        "about real time, one run at a time",
    )
    ap.add_argument(
        "--machine",
        help="run every scenario on this machine card (per-unit "
        "speeds scale with its rated speed, defaults derive from it; results go "
        "to results/experiments-<card> unless --out)",
    )
    args = ap.parse_args(argv)
    if args.machine:
        from fluxdrive.core.machine import load_machine

        card = load_machine(machine_path(args.machine))  # refuse a bad card up front
        common._MACHINE["path"] = str(machine_path(args.machine).resolve())
        args.out = args.out or REPO_ROOT / "results" / f"experiments-{card.name}"
    if args.graph:
        if common._RUNNER["graph"] is None:
            raise ConfigError("--graph runs through the ROS graph: use ./fluxdrive experiment")
        args.workers = 1  # a graph run uses both cores
    if args.name == "list":
        for k, (_, title) in reg.items():
            print(f"{k:18s} {title}")
        return 0
    names = list(reg) if args.name == "all" else args.name.split(",")
    bad = [n for n in names if n not in reg]
    if bad:
        print(f"unknown experiment(s) {bad}; known: {', '.join(reg)}", file=sys.stderr)
        return 2
    out = args.out or REPO_ROOT / "results" / "experiments"
    t0 = time.perf_counter()
    from fluxdrive.study.runner import runner_from_args
    from fluxdrive.study.tasks import warm_kernels

    if args.workers > 1 and not args.scheduler and not args.graph:
        warm_kernels()  # compiled once here, loaded from the cache by the local workers
    runner = runner_from_args(None if args.graph else args.scheduler, args.workers)
    judged: list[dict] = []
    try:
        for n in names:
            sys.stderr.write(f"== experiment {n} ({time.perf_counter() - t0:.0f} s elapsed)\n")
            try:
                res = run_experiment(n, out, args.quick, runner)
            except Exception as exc:  # one broken experiment must not lose the others
                import traceback

                traceback.print_exc()
                res = {
                    "title": n,
                    "runtime_s": 0.0,
                    "quick": args.quick,
                    "figures": [],
                    "claims": [
                        claim(
                            "experiment ran",
                            f"failed: {exc!r}",
                            False,
                            "see the traceback on stderr",
                        )
                    ],
                }
            write_report(out, {n: res})
            for c in res["claims"]:
                print(f"[{n}] {_fmt_verdict(c):22s} {c['claim']}  ->  {c['ours']}")
            print(f"[{n}] {res['runtime_s']:.1f} s")
            judged += res["claims"]
    finally:
        runner.close()
    print(f"claims: {counts_line(count(judged))}")
    print(f"report: {out / 'report.md'} ({time.perf_counter() - t0:.1f} s total)")
    return 0
