"""`./fluxdrive study SPEC.yaml --out DIR ...`: the command line of a study
(fluxdrive.study.cli.run_study: sweeps and Monte-Carlo robustness maps on dask)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from fluxdrive.core.machine import ConfigError, load_machine
from fluxdrive.core.schema import Parser
from fluxdrive.drive.scenario import MACHINE_HELP, REPO_ROOT, load_scenario, machine_path
from fluxdrive.study import cli as study_cli
from fluxdrive.study.cli import run_study
from fluxdrive.study.runner import runner_from_args
from fluxdrive.study.spec import StudySpec, load_spec
from fluxdrive.study.tasks import warm_kernels


def on_machine(spec: StudySpec, machine: str) -> str:
    """`--machine`: every task's motor is this card (the spec's scenario.machine replaced);
    the line saying what was kept."""
    card = machine_path(machine).resolve()
    load_machine(card)  # a bad card: refused here, in one line, before any task
    spec.scenario["machine"] = str(card)
    if "file" in spec.scenario:
        return load_scenario(spec.scenario["file"], machine=card).machine_note
    what = "the recorded bag's" if spec.kind == "bag" else f"builder {spec.scenario['builder']}'s"
    return f"--machine {card.stem}: the motor from its card, everything else {what}"


def main(argv: list[str]) -> int:
    ap = Parser(
        prog="fluxdrive study",
        description=study_cli.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("spec", help="study spec YAML (path, or a name under config/studies)")
    ap.add_argument(
        "--out",
        type=Path,
        help="output folder (default runs/study-<name>); "
        "an existing one is resumed (or extended: more draws, points, variants)",
    )
    ap.add_argument(
        "--scheduler",
        help="run on an existing dask cluster: tcp://HOST:PORT "
        "(started with `dask scheduler` and `dask worker`)",
    )
    ap.add_argument(
        "--workers",
        type=int,
        help="LocalCluster worker processes (default: every core; 1 runs in-process)",
    )
    ap.add_argument("--machine", help=MACHINE_HELP)
    ap.add_argument("--restart", action="store_true", help="discard what --out holds")
    ap.add_argument(
        "--maps-only",
        action="store_true",
        help="redo the maps and report from the table, run nothing",
    )
    args = ap.parse_args(argv)
    spec = load_spec(args.spec)
    if args.machine is not None:
        print(on_machine(spec, args.machine), flush=True)
    out = args.out or REPO_ROOT / "runs" / f"study-{spec.name}"
    if args.maps_only:
        from fluxdrive.study import maps, store

        t = store.read_table(out)
        if t is None:
            raise ConfigError(f"{out}: no study table (results.parquet) to map")
        info: dict[str, Any] = {"tasks": len(spec.tasks())}
        if (out / "summary.json").exists():  # how the table was made: keep it in the report
            prev = json.loads((out / "summary.json").read_text())
            info.update(
                runner=prev.get("runner", ""),
                elapsed_s=prev.get("elapsed_s", 0.0),
                commit=prev.get("commit", "?"),
            )
        fails = (
            [json.loads(x) for x in (out / "failures.jsonl").read_text().splitlines()]
            if (out / "failures.jsonl").exists()
            else []
        )
        rep = maps.write_report(t, spec, out, fails, info)
        print(json.dumps(rep["lowest"], default=str))
        return 0
    if spec.kind == "scenario" and not args.scheduler:
        warm_kernels()  # compiled once here, loaded from the cache by the local workers
    with runner_from_args(args.scheduler, args.workers) as runner:
        s = run_study(spec, out, runner, restart=args.restart)
    for v, r in s["lowest_speed"].items():
        print(
            f"{v}: holds {r['load_pu']:g} pu with P^ >= {spec.probability:g} down to "
            f"{r['point_rpm']} rpm (Wilson-confident: {r['confident_rpm']})"
        )
    print(
        f"{s['rows']}/{s['tasks']} rows, {s['failed']} failed, {s['elapsed_s']:.0f} s; "
        f"report: {out / 'report.md'}"
    )
    return 1 if s["failed"] else 0


# ---------------------------------------------------------------- benchmark
