"""`./fluxdrive experiment NAME[,NAME...]|paper|beyond|all|list [--quick] [--graph]
[--machine CARD] [--bench FILE] [--out DIR]`:
the paper's figures (`paper`: all of them, one report, the total wall time printed last), and
past them (`beyond`) (fluxdrive.experiments).  `--graph` runs every scenario
through the ROS node graph instead of in-process (entered through the graph tools, which pass
their runner in)."""

from __future__ import annotations

import argparse
import os
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from fluxdrive.core.machine import ConfigError, load_machine
from fluxdrive.core.schema import Parser
from fluxdrive.drive.scenario import MACHINE_HELP, REPO_ROOT, load_bench_file, machine_path
from fluxdrive.experiments.claims import BEYOND, MIN_SEEDS, count, counts_line
from fluxdrive.experiments.common import DEFAULT_MACHINE
from fluxdrive.experiments.registry import (
    expand,
    experiments,
    fmt_verdict,
    groups,
    run_experiments,
    write_report,
)


def _parser(names: list[str]) -> argparse.ArgumentParser:
    ap = Parser(
        prog="fluxdrive experiment",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument(
        "name",
        help="experiment names (comma-separated), a group (paper: the paper's figures, "
        "beyond, all) or 'list': " + ", ".join(names),
    )
    ap.add_argument("--quick", action="store_true", help="fewer points, shorter runs")
    ap.add_argument(
        "--seeds",
        type=int,
        metavar="N",
        help="noise seeds per verdict of an experiment that runs one seed (1..64; default "
        f"{MIN_SEEDS}, 1 with --quick)",
    )
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
        "--bench",
        type=Path,
        help="run every scenario that uses the paper bench (config/benches/paper_lab.yaml) "
        "on this bench file instead (ideal runs stay ideal; results go to "
        "results/bench-<file> unless --out)",
    )
    ap.add_argument(
        "--against",
        type=Path,
        help="a results folder of the same experiments (e.g. on another bench): write "
        "deltas.json, each claim's value and verdict there and here (name 'deltas': only "
        "that, from the report already in --out)",
    )
    ap.add_argument(
        "--machine",
        help=MACHINE_HELP + " (results go to results/experiments-<card> unless --out)",
    )
    return ap


def verdict_deltas(base: dict, new: dict) -> dict:
    """Claim by claim (matched on id), the value and verdict of `base` and `new` (two
    report.json mappings), and the counts of verdicts that changed; `reproduction`: of the
    reproductions both judged (the claims about the observers themselves, not a number
    calibrated on or designed for one card), which hold in both, in one only, in neither."""

    def claims(rep: dict) -> dict[str, dict]:
        return {
            c.get("id") or c["claim"]: {**c, "experiment": name}
            for name, e in rep.get("experiments", {}).items()
            for c in e.get("claims", [])
        }

    b, n = claims(base), claims(new)
    rows = []
    for cid in [k for k in n if k in b] + [k for k in b if k not in n]:
        cb, cn = b.get(cid, {}), n.get(cid, {})
        rows.append(
            {
                "id": cid,
                "experiment": (cn or cb)["experiment"],
                "claim": (cn or cb)["claim"],
                "base_value": cb.get("value"),
                "new_value": cn.get("value"),
                "base_verdict": cb.get("verdict", fmt_verdict(cb) if cb else None),
                "new_verdict": cn.get("verdict", fmt_verdict(cn) if cn else None),
                "base_ours": cb.get("ours"),
                "new_ours": cn.get("ours"),
            }
        )
    changed = [r for r in rows if r["base_verdict"] != r["new_verdict"]]
    repro = [r for r in rows if r["id"] in b and b[r["id"]].get("class") == "reproduction"]
    repro = [r for r in repro if r["id"] in n and n[r["id"]].get("class") == "reproduction"]

    def held(r: dict, *sides: str) -> bool:
        return all(r[f"{side}_verdict"] == "held" for side in sides)

    return {
        "claims": len(rows),
        "verdicts_changed": len(changed),
        "changed": changed,
        "reproduction": {
            "claims": len(repro),
            "held_both": [r["id"] for r in repro if held(r, "base", "new")],
            "held_base_only": [r["id"] for r in repro if held(r, "base") and not held(r, "new")],
            "held_new_only": [r["id"] for r in repro if held(r, "new") and not held(r, "base")],
            "held_neither": [r["id"] for r in repro if not held(r, "base") and not held(r, "new")],
        },
        "counts_base": count([c for c in b.values()]),
        "counts_new": count([c for c in n.values()]),
        "rows": rows,
    }


def _write_deltas(against: Path, out: Path) -> None:
    import json

    reports = []
    for d in (against, out):
        try:
            reports.append(json.loads((d / "report.json").read_text()))
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{d / 'report.json'}: cannot read the report: {exc}") from None
    deltas = verdict_deltas(*reports)
    deltas["base_dir"] = str(against)
    (out / "deltas.json").write_text(json.dumps(deltas, indent=1, default=str))
    for r in deltas["rows"]:
        if r["base_verdict"] != r["new_verdict"]:
            print(f"changed: {r['id']}: {r['base_verdict']} -> {r['new_verdict']}")
    print(f"deltas: {deltas['verdicts_changed']} of {deltas['claims']} verdicts changed")
    rep = deltas["reproduction"]
    print(
        f"reproductions judged in both: {rep['claims']}; held in both {len(rep['held_both'])}, "
        f"only in {against} {len(rep['held_base_only'])}, only here "
        f"{len(rep['held_new_only'])}, in neither {len(rep['held_neither'])}"
    )
    print(f"written: {out / 'deltas.json'}")


def _failed(name: str, quick: bool, exc: Exception) -> dict:
    """The report entry of an experiment that raised (the others still run)."""
    traceback.print_exc()
    return {
        "title": name,
        "runtime_s": 0.0,
        "quick": quick,
        "figures": [],
        "claims": [
            {"claim": "experiment ran", "ours": f"failed: {exc!r}", "error": "see the traceback"}
        ],
    }


def _run_all(
    args: argparse.Namespace,
    names: list[str],
    machine: Path | None,
    graph_run: Callable | None,
    out: Path,
) -> list[dict]:
    """Run the experiments (on a cluster all at once, in-process in order), each written to
    the report as it ends."""
    from fluxdrive.study.runner import runner_from_args
    from fluxdrive.study.tasks import warm_kernels

    t0 = time.perf_counter()
    if args.workers > 1 and not args.scheduler and graph_run is None:
        warm_kernels()  # compiled once here, loaded from the cache by the local workers
    runner = runner_from_args(None if graph_run else args.scheduler, args.workers)
    judged: list[dict] = []

    def done(n: str, res: dict) -> None:  # each experiment into the report as it ends
        write_report(out, {n: res})
        for c in res["claims"]:
            print(f"[{n}] {fmt_verdict(c):22s} {c['claim']}  ->  {c['ours']}")
        print(f"[{n}] {res['runtime_s']:.1f} s ({time.perf_counter() - t0:.0f} s elapsed)")
        judged.extend(res["claims"])

    sys.stderr.write(f"== experiments {', '.join(names)} on {runner.address}\n")
    try:
        run_experiments(
            names,
            out,
            done,
            lambda n, exc: _failed(n, args.quick, exc),
            runner,
            quick=args.quick,
            machine=machine,
            graph_run=graph_run,
            bench=args.bench,
            seeds=args.seeds,
        )
    finally:
        runner.close()
    paper = [c for c in judged if c.get("class") != BEYOND]
    print(f"claims: {counts_line(count(paper))}")
    if len(paper) < len(judged):
        print(f"past the paper: {counts_line(count([c for c in judged if c not in paper]))}")
    print(
        f"report: {out / 'report.md'} ({len(names)} experiments, "
        f"{time.perf_counter() - t0:.1f} s wall total, load average {os.getloadavg()[0]:.1f})"
    )
    return judged


def main(argv: list[str], graph_run: Callable | None = None) -> int:
    """The command; `graph_run` (scenario -> SimResult through the node graph) is what the
    graph tools pass in for --graph."""
    reg = experiments()
    ap = _parser(list(reg))
    args = ap.parse_args(argv)
    if args.seeds is not None and not 1 <= args.seeds <= 64:
        ap.error(f"--seeds: {args.seeds} is not in 1..64")
    machine = None
    out = args.out
    if args.machine:
        card = load_machine(machine_path(args.machine))  # refuse a bad card up front
        machine = machine_path(args.machine).resolve()
        out = out or REPO_ROOT / "results" / f"experiments-{card.name}"
        print(
            f"--machine {card.name}: the motor of every run; the scenario files the runs start "
            "from keep their rig (load inertia and friction, PWM, deadtime, sensors), the "
            "scenarios built in memory have no rig beyond the card",
            flush=True,
        )
    if args.bench:
        load_bench_file(args.bench, load_machine(machine or DEFAULT_MACHINE))  # refuse early
        out = out or REPO_ROOT / "results" / f"bench-{args.bench.stem}"
    if args.graph:
        if graph_run is None:
            raise ConfigError("--graph runs through the ROS graph: use ./fluxdrive experiment")
        args.workers = 1  # a graph run uses both cores
    else:
        graph_run = None
    if args.name == "list":
        for k, (_, title) in reg.items():
            print(f"{k:18s} {title}")
        for g, members in groups().items():
            print(f"{g:18s} group: {', '.join(members)}")
        return 0
    out = out or REPO_ROOT / "results" / "experiments"
    if args.name == "deltas":
        if args.against is None:
            raise ConfigError("experiment deltas: give --against DIR (and --out DIR)")
        _write_deltas(args.against, out)
        return 0
    names = expand(args.name)
    bad = [n for n in names if n not in reg]
    if bad:
        print(f"unknown experiment(s) {bad}; known: {', '.join(reg)}", file=sys.stderr)
        return 2
    _run_all(args, names, machine, graph_run, out)
    if args.against is not None:
        _write_deltas(args.against, out)
    return 0
