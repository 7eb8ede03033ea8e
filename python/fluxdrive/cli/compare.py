"""`./fluxdrive compare VARIANT... [--speeds PU,...] [--loads PU,...] [--sources ...]`:
Pareto fronts of θ̃ (RMS, broadband noise, 6th order) against the speed-loop bandwidth each
observer's speed path allows, for any set of observer variants -- built-in names or a user's
`module:Class`, each with fixed settings as replay takes them (`TARGET:key=value,...`) --
sweeping each one's PLL (and the EMF path's speed LPF with it) and, where it has one, its flux
cutoff.  Every variant runs in shadow on the same encoder-driven runs, one per operating
point; the fronts come from the `fronts` experiment's code (fluxdrive.experiments.fronts).
Writes compare.json and compare.png (default out/compare/; `--write`: the tracked
results/compare/).  A plugin gets the sweep as constructor keywords (--pll-key,
--cutoff-key); the last line printed is the JSON summary."""

from __future__ import annotations

import argparse
import json
import os
import re
from pathlib import Path
from typing import Any

from fluxdrive.core.machine import ConfigError
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.observers import observer_config
from fluxdrive.drive.scenario import REPO_ROOT, load_bench_file, machine_path
from fluxdrive.experiments import fronts as fr
from fluxdrive.experiments.common import Ctx
from fluxdrive.replay.lab import parse_variant


def _floats(text: str, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--{what}: a comma-separated list of numbers, got {text!r}") from None
    if not vals or any(v < 0.0 for v in vals):
        raise ConfigError(f"--{what}: non-negative numbers, got {text!r}")
    return vals


def _parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog="fluxdrive compare",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("variants", nargs="+", help="observer variants (name or module:Class)")
    ap.add_argument("--speeds", default="0.02,0.1", help="speeds [pu of rated] (0.02,0.1)")
    ap.add_argument("--loads", default="1.5,0", help="brake loads [pu of rated torque] (1.5,0)")
    ap.add_argument(
        "--sources", default="measured,commanded", help="voltage sources (measured,commanded)"
    )
    ap.add_argument("--quick", action="store_true", help="coarse sweep")
    option(ap, "--settle-s", fr.FrontWindow)
    option(ap, "--window-s", fr.FrontWindow)
    ap.add_argument("--machine", help="machine card (default: the default card)")
    ap.add_argument("--bench", type=Path, help="bench file the runs use (default: ideal)")
    ap.add_argument("--pll-key", default="pll_hz", help="a plugin's PLL keyword [Hz]")
    ap.add_argument("--cutoff-key", default="cutoff_hz", help="a plugin's flux cutoff [Hz]")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument(
        "--out",
        type=Path,
        help="output folder (default out/compare; with --write results/compare)",
    )
    ap.add_argument(
        "--write", action="store_true", help="write the tracked results/compare/ (regenerate it)"
    )
    return ap


def families_of(variants: list[str]) -> dict[str, str]:
    """Family name (the variant's label, made a plain identifier) -> variant spec, each one
    validated (an unknown name, a plugin that does not load or a bad `key=value`: one
    line).  A spec is replay's: `[label=]TARGET[:key=value,...]`, TARGET a built-in name or
    `module:Class`; its settings are fixed, the PLL and cutoff are swept."""
    fams: dict[str, str] = {}
    for v in variants:
        spec = parse_variant(v)
        cfg = observer_config(spec.target)
        if spec.params and ":" not in spec.target:
            cfg.with_overrides(**spec.params)  # a key the variant lacks: one line, here
        label = v.split("=", 1)[0] if spec.label and v.startswith(spec.label + "=") else ""
        last = label or re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", spec.target.rsplit(":", 1)[-1])
        name = re.sub(r"\W+", "_", last).strip("_").lower() or "variant"
        if spec.params and not label:
            name += "_" + "_".join(re.sub(r"\W+", "_", f"{k}_{x}") for k, x in spec.params.items())
        while name in fams:
            name += "_"
        target = spec.target + (
            ":" + ",".join(f"{k}={x}" for k, x in spec.params.items()) if spec.params else ""
        )
        fams[name] = target
    return fams


def summary(data: dict[str, Any], families: dict[str, str]) -> dict[str, Any]:
    """Per cell and family: the fronts (bandwidth, θ̃) and the highest bandwidth the family
    reaches; with two or more families, the first over the second on the RMS and noise
    fronts at equal allowed bandwidth (`first_over_second`)."""
    out: dict[str, Any] = {}
    names = list(families)
    for key, cell in data.items():
        out[key] = {
            fam: {
                "variant": families[fam],
                "front_rms": cell[fam]["front_rms"],
                "front_noise": cell[fam]["front_noise"],
                "front_h6": cell[fam]["front_h6"],
                # None: every setting slipped (no front)
                "max_bandwidth_hz": max((p[0] for p in cell[fam]["front_rms"]), default=None),
            }
            for fam in families
        }
        if len(names) >= 2:
            out[key]["first_over_second"] = {
                q: fr.matched_ratio(cell, names[0], names[1], f"front_{q}")
                for q in ("rms", "noise")
            }
    return out


def out_folder(args: argparse.Namespace) -> Path:
    """Where compare writes: --out, else results/compare/ (tracked) only with --write, else
    out/compare/ (untracked), so a trial run never rewrites the committed results."""
    if args.out is not None:
        return Path(args.out)
    return REPO_ROOT / ("results" if args.write else "out") / "compare"


def run(args: argparse.Namespace) -> dict[str, Any]:
    from fluxdrive.study.runner import runner_from_args

    args.out = out_folder(args)

    families = families_of(args.variants)
    sources = tuple(s.strip() for s in args.sources.split(",") if s.strip())
    bad = [s for s in sources if s not in fr.SOURCES]
    if bad:
        raise ConfigError(f"--sources: {bad} unknown; use {', '.join(fr.SOURCES)}")
    points = [
        (s, ld) for s in _floats(args.speeds, "speeds") for ld in _floats(args.loads, "loads")
    ]
    machine = machine_path(args.machine).resolve() if args.machine else None
    runner = runner_from_args(None, args.workers)
    ctx = Ctx(out=args.out, quick=args.quick, runner=runner, name="compare", machine=machine)
    try:
        keys = {"pll": args.pll_key, "cutoff": args.cutoff_key}
        bench = None
        if args.bench is not None:
            load_bench_file(args.bench, ctx.card)  # a bad file: one line, before any run
            bench = str(args.bench.resolve())
        data = fr.run_fronts(
            ctx, families, points, sources, keys, args.settle_s, args.window_s, bench
        )
    finally:
        runner.close()
    figure = fr.plot(ctx, data, families, name="compare")
    result = {
        "variants": families,
        "card": ctx.card.name,
        "bench": str(args.bench) if args.bench else "ideal",
        "points": points,
        "sources": list(sources),
        "quick": args.quick,
        "figure": figure,
        "fronts": summary(data, families),
        "cells": data,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compare.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    result = run(args)
    for key, cell in result["fronts"].items():
        for fam, f in cell.items():
            if fam == "first_over_second":
                continue
            best = min(e for _, e in f["front_rms"])
            print(
                f"{key:28s} {fam:16s} θ̃ RMS best {best:.2f}° ; up to "
                f"{f['max_bandwidth_hz']:.1f} Hz speed-loop bandwidth"
            )
    print(f"written: {args.out / 'compare.json'}, {args.out / result['figure']}")
    print(json.dumps({"variants": result["variants"], "fronts": result["fronts"]}))
    return 0
