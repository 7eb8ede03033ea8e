"""`./fluxdrive replay BAG... --variant SPEC ...`: the command line of the replay lab
(fluxdrive.replay.lab) and of its sweeps (fluxdrive.study.bagsweep); `--live` is sent to
fluxdrive_bringup.replay.live_replay, which shares this parser."""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

from fluxdrive.analysis.metrics import compute, format_table, write_json
from fluxdrive.core.machine import ConfigError, load_machine
from fluxdrive.core.paths import check_output
from fluxdrive.core.schema import Parser
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive.io.bagio import BagError, RunBag, read_run_bag
from fluxdrive.replay import lab
from fluxdrive.replay.lab import (
    expand_variants,
    format_sweep,
    live_changes,
    markdown_section,
    parse_sweep,
    plot_replay,
    replay_bag,
    slug,
    write_augmented_bag,
)
from fluxdrive.study.bagsweep import sweep_bag


def _parse_window(s: str | None) -> tuple[float, float] | None:
    if not s:
        return None
    try:
        a, b = (float(x) for x in s.split(":"))
    except ValueError:
        raise ConfigError(f"--window '{s}': expected START:END in seconds") from None
    if not (math.isfinite(a) and math.isfinite(b) and 0.0 <= a < b):
        raise ConfigError(f"--window '{s}': expected finite seconds 0 <= START < END")
    return (a, b)


def build_parser() -> argparse.ArgumentParser:
    """`fluxdrive replay`'s options (the live publisher in fluxdrive_bringup shares them)."""
    ap = Parser(
        prog="fluxdrive replay",
        description=lab.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("bags", nargs="+", type=Path, help="rosbag2 folders (mcap)")
    ap.add_argument(
        "--variant",
        "-v",
        action="append",
        default=[],
        help="variant SPEC (repeatable); default: @recorded, else paper",
    )
    ap.add_argument("--out", type=Path, help="output folder (default runs/replay-<time>)")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument(
        "--write-bag",
        type=Path,
        help="write a new bag: frames, truth and the "
        "recorded estimates, plus every variant's estimates as /obs/<label>/estimate",
    )
    ap.add_argument("--machine", help="machine card (default: the one recorded in the bag)")
    ap.add_argument(
        "--window",
        help="metrics window START:END [s] (default: recorded, or the second half of the bag)",
    )
    ap.add_argument(
        "--encoder-offset-deg",
        type=float,
        default=0.0,
        help="electrical offset of the encoder (bags without /drive/truth)",
    )
    ap.add_argument(
        "--card-model",
        action="store_true",
        help="new variants use the machine card's R, L, lambda as their model instead of "
        "the observer model the bag records (the default)",
    )
    ap.add_argument("--sweep", help="KEY=START:STOP:N or KEY=V1,V2,.. over the (single) variant")
    ap.add_argument(
        "--jobs",
        "-j",
        type=int,
        default=os.cpu_count() or 1,
        help="sweep: worker processes of the local dask cluster (1: in-process)",
    )
    ap.add_argument("--scheduler", help="sweep: run on an existing dask cluster tcp://HOST:PORT")
    ap.add_argument("--live", action="store_true", help="publish the frames on /drive/frame")
    ap.add_argument("--rate", type=float, default=1.0, help="live: factor of real time")
    ap.add_argument("--loop", action="store_true", help="live: start again at the end")
    ap.add_argument("--start", type=float, default=0.0, help="live: offset into the bag [s]")
    ap.add_argument(
        "--wait-s",
        type=float,
        default=2.0,
        help="live: wait this long for a first subscriber before publishing",
    )
    ap.add_argument("--max-frames", type=int, help=argparse.SUPPRESS)
    ap.add_argument(
        "--graph-id",
        type=int,
        help="live: graph_id stamped on the frames (the "
        "graph they feed: ./fluxdrive param get /plant graph_id; default: the "
        "launch's, else 0 = not in a launched graph)",
    )
    return ap


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _main(args)
    except BagError as exc:
        print(f"fluxdrive replay: {exc}", file=sys.stderr)
        return 2


def _main(args) -> int:
    if args.live:  # the command line sends --live to fluxdrive_bringup.replay.live_replay (ROS)
        raise ConfigError("--live publishes on the ROS graph: run it as ./fluxdrive replay")
    machine = load_machine(args.machine) if args.machine else None
    window = _parse_window(args.window)
    out = args.out or REPO_ROOT / "runs" / f"replay-{time.strftime('%Y%m%d-%H%M%S')}"
    check_output(out, "--out")
    if args.write_bag is not None:
        check_output(args.write_bag, "--write-bag")
    if args.sweep:
        return _sweep(args, window, out)
    metrics_all: dict[str, Any] = {}
    md = [
        "# Replay report",
        "",
        f"variants: {', '.join('`' + v + '`' for v in (args.variant or ['(default)']))}",
        "",
    ]
    for bp in args.bags:
        bag = _read(bp)
        specs = args.variant or (["@recorded"] if bag.meta.get("observers") else ["paper"])
        variants = expand_variants(specs, bag)
        res = replay_bag(
            bag, variants, machine, window, args.encoder_offset_deg, card_model=args.card_model
        )
        m = _report_bag(bag, variants, res)
        key = slug(bag.path.name)
        while key in metrics_all:
            key += "_"
        metrics_all[key] = m
        if not args.no_plots:
            plots = plot_replay(res, out / key)
            md.append(markdown_section(res, m, plots, out))
        if args.write_bag is not None:
            wb = args.write_bag if len(args.bags) == 1 else args.write_bag / key
            write_augmented_bag(res, bag, wb)
            print(f"wrote {wb} (+ {len(res.names)} estimate topics)")
    out.mkdir(parents=True, exist_ok=True)
    write_json(metrics_all, out / "metrics.json")
    if not args.no_plots:
        (out / "report.md").write_text("\n".join(md) + "\n")
        print(f"saved: {out}/report.md, metrics.json, <bag>/*.png")
    else:
        print(f"saved: {out}/metrics.json")
    return 0


def _sweep(args, window: tuple[float, float] | None, out: Path) -> int:
    """--sweep: the one variant over the values of one setting, per bag."""
    if len(args.variant) > 1:
        raise ConfigError("--sweep takes one --variant")
    key, values = parse_sweep(args.sweep)
    for bp in args.bags:
        bag = _read(bp)
        vs = expand_variants(args.variant or ["paper"], bag)[0]
        od = out / slug(bag.path.name) if len(args.bags) > 1 else out
        where = args.scheduler or f"{args.jobs} processes"
        print(
            f"sweep {vs.target} {key} over {len(values)} values on {bag.path} "
            f"({bag.n} frames, {where})"
        )
        note = lab.sweep_marker_note(bag, vs, key)
        if note:
            print(f"   {note}")
        rows = sweep_bag(
            bag,
            vs,
            key,
            values,
            args.jobs,
            od,
            args.machine,
            window,
            args.encoder_offset_deg,
            args.scheduler,
        )
        print(format_sweep(rows, key))
        for r in rows:
            if r.get("recorded_max_abs_diff") is not None:
                print(
                    f"   {key}={r[key]:g} keeps the recorded settings: "
                    f"max |replayed - recorded| = {r['recorded_max_abs_diff']:.3g}"
                )
        print(f"saved: {od}/sweep.json, sweep.png")
    return 0


def _report_bag(bag: RunBag, variants: list, res: lab.ReplayResult) -> dict[str, Any]:
    """One bag's metrics (with where its reference and model came from), printed."""
    m = compute(res)
    m["truth_source"] = res.truth_source
    m["frames"] = bag.n
    m["problems"] = bag.problems
    m["recorded_max_abs_diff"] = res.recorded_diff
    m["replay_wall_s"] = res.wall_s
    print(f"== {bag.path} ({bag.n} frames, reference: {res.truth_source})")
    if any(v.recorded is None for v in variants):
        print(
            "   new variants' observer model: "
            + ", ".join(f"{k} {v:.6g}" for k, v in res.model.items())
            + f" from {res.model_source} (a variant's own r_hat_ohm=... wins)"
        )
    m["observer_model"] = {"values": res.model, "source": res.model_source}
    print(format_table(m))
    for nm, d in res.recorded_diff.items():
        print(f"   {nm}: max |replayed - recorded| = {d:.3g}")
    applied = {
        v.label: len(live_changes(bag, v))
        for v in variants
        if v.recorded is not None and live_changes(bag, v)
    }
    if applied:
        print(
            "   live parameter changes applied from the bag's markers: "
            + ", ".join(f"{k} {n}" for k, n in applied.items())
        )
    return m


def _read(path: Path) -> RunBag:
    bag = read_run_bag(path)
    for pr in bag.problems:
        print(f"fluxdrive replay: {path}: partial bag: {pr}", file=sys.stderr)
    return bag
