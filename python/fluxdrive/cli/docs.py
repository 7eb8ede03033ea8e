"""`./fluxdrive docs build|serve|quotes`: the docs site and the figures it quotes.

./fluxdrive docs build [--out DIR]   mkdocs build --strict (links and anchors checked) into
                                     DIR (default .ws/site)
./fluxdrive docs serve               mkdocs serve on 127.0.0.1:8000 (live reload)
./fluxdrive docs quotes [--check]    fill the quoted figures of README.md and docs/*.md from
                                     results/ (--check: only say which files are stale)
./fluxdrive docs params [--check]    write the parameter tables of docs/configuration.md from
                                     the config schemas, the graph file's tables of
                                     docs/graph.md from its schema and the node tables there
                                     from the nodes (--check: only say which are stale)
./fluxdrive docs tour                run the shipped scenarios in-process and write
                                     results/tour/scenarios.json, which docs/tour.md quotes
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

from fluxdrive.analysis.quotes import QuoteError, count, fill, quoted_files, stale
from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import Parser


def build(out: str, quiet: bool = False) -> int:
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml")]
    return subprocess.call([*cmd, "-d", out, *(["-q"] if quiet else [])], cwd=ROOT)


def quotes(check: bool) -> int:
    files = quoted_files()
    try:
        if check:
            bad = stale(files)
            for p in bad:
                print(
                    f"{p.relative_to(ROOT)}: quoted figures differ from results/ "
                    "(run ./fluxdrive docs quotes)",
                    file=sys.stderr,
                )
            print(f"{count(files)} quoted figures in {len(files)} files; {len(bad)} stale")
            return 1 if bad else 0
        changed = 0
        for p in files:
            text = p.read_text()
            new = fill(text, str(p.relative_to(ROOT)))
            if new != text:
                p.write_text(new)
                changed += 1
                print(f"updated {p.relative_to(ROOT)}")
        print(f"{count(files)} quoted figures in {len(files)} files; {changed} files updated")
        return 0
    except QuoteError as exc:
        print(f"docs quotes: {exc}", file=sys.stderr)
        return 1


def param_tables(check: bool) -> int:
    """The config blocks' tables of docs/configuration.md, the study spec's of
    docs/study.md, the graph file's of docs/graph.md and identify's options of
    docs/machines.md, written from their schemas (or checked)."""
    from fluxdrive.drive import config_blocks, identify
    from fluxdrive.io import graphfile
    from fluxdrive.study import spec

    pages = [
        (config_blocks.DOC_PAGE, config_blocks.docs_tables()),
        (spec.DOC_PAGE, spec.docs_tables()),
        (graphfile.DOC_PAGE, graphfile.docs_tables()),
        (identify.DOC_PAGE, identify.docs_tables()),
    ]
    return max(_page_tables(page, tables, check) for page, tables in pages)


def _page_tables(path, tables: dict[str, str], check: bool) -> int:
    from fluxdrive.drive import config_blocks

    page = path.relative_to(ROOT)
    if check:
        bad = config_blocks.stale_tables(tables, path)
        for key in bad:
            print(f"{page}: the '{key}' table differs from its schema", file=sys.stderr)
        print(f"{len(tables)} config blocks; {len(bad)} stale tables in {page}")
        return 1 if bad else 0
    text = path.read_text()
    try:
        new = config_blocks.fill(text, tables, path)
    except ValueError as exc:
        print(f"docs params: {exc}", file=sys.stderr)
        return 1
    missing = [k for k in tables if f"<!-- params {k} -->" not in new]
    for key in missing:
        print(f"{page}: no table for '{key}' (add <!-- params {key} --><!-- /params -->)")
    if new != text:
        path.write_text(new)
    state = "updated" if new != text else "current"
    print(f"{len(tables)} config blocks; {page} {state}")
    return 1 if missing else 0


# the node tables of docs/graph.md are read from the nodes: ROS, so from the graph package
NODE_TABLES = "fluxdrive_bringup.inspect.paramdoc"


def node_tables(check: bool) -> int:
    """The node parameter tables of docs/graph.md written (or checked) in a process of their
    own (the nodes start there; the engine never imports ROS)."""
    cmd = [sys.executable, "-m", NODE_TABLES, "--check" if check else "--write"]
    return subprocess.call(cmd, cwd=ROOT)


TOUR_RESULTS = ROOT / "results" / "tour" / "scenarios.json"
TOUR_EXAMPLE = "paper_2pct_150load"  # the scenario whose printed table the tour shows


def tour_results(out: Path = TOUR_RESULTS) -> int:
    """Run every shipped scenario in-process (the seed in its file) as `./fluxdrive sim`
    does and write what docs/tour.md quotes: per scenario whether it is stable, the driving
    observer's θ̃ RMS, the trip if any, the mean speed; for TOUR_EXAMPLE the metric table
    `sim` prints, as a Markdown code block, and every observer's θ̃ RMS and 6th order."""
    import json

    from fluxdrive.analysis.metrics import compute, format_table
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
    from fluxdrive.drive.sim import run_scenario

    data: dict[str, Any] = {}
    for path in sorted((CONFIG_DIR / "scenarios").glob("*.yaml")):
        sc = load_scenario(path)
        res = run_scenario(sc, progress=False)
        m = compute(res)
        drv = m["observers"].get(m["driving"], {})
        row: dict[str, Any] = {
            "stable": m["stable"],
            "stable_text": "stable" if m["stable"] else "not stable",
            "driving": m["driving"],
            "seed": sc.seed,
            "rms_deg": drv.get("theta_err_rms_deg"),
            "speed_mean_rpm": m["speed"]["mean_rpm"],
            "trip": (m["trip"] or {}).get("message", ""),
            "simulated_s": sc.duration_s,
            "wall_s": res.wall_s,
        }
        if sc.name == TOUR_EXAMPLE:
            obs = m["observers"]
            # on lines of their own: the quote's markers stay outside the code block
            row["table"] = f"\n```\n{format_table(m)}\n```\n"
            row["observers"] = {
                nm: {"rms_deg": o["theta_err_rms_deg"], "h6_deg": o["theta_err_h6_deg"]}
                for nm, o in obs.items()
            }
            row["lowest_rms"] = min(obs, key=lambda nm: obs[nm]["theta_err_rms_deg"])
        data[sc.name] = row
        print(f"{sc.name}: {row['stable_text']}, θ̃ RMS {row['rms_deg']}", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1, default=float) + "\n")
    print(f"written: {out}; now ./fluxdrive docs quotes")
    return 0


def main(argv: list[str]) -> int:
    ap = Parser(
        prog="fluxdrive docs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="build the site (strict: links and anchors checked)")
    b.add_argument("--out", default=str(ROOT / ".ws" / "site"))
    sub.add_parser("serve", help="serve the site on 127.0.0.1:8000 while editing")
    q = sub.add_parser("quotes", help="fill quoted figures from results/")
    q.add_argument("--check", action="store_true", help="only report stale files (exit 1)")
    pt = sub.add_parser("params", help="write the parameter tables from the config schemas")
    pt.add_argument("--check", action="store_true", help="only report stale tables (exit 1)")
    sub.add_parser(
        "tour", help="run the shipped scenarios and write results/tour/ (docs/tour.md quotes it)"
    )
    args = ap.parse_args(argv)
    if args.cmd == "tour":
        return tour_results()
    if args.cmd == "build":
        return build(args.out)
    if args.cmd == "serve":
        cmd = [sys.executable, "-m", "mkdocs", "serve", "-a", "127.0.0.1:8000"]
        return subprocess.call(cmd, cwd=ROOT)
    if args.cmd == "params":
        return param_tables(args.check) | node_tables(args.check)
    return quotes(args.check)
