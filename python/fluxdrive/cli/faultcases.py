"""`./fluxdrive fault-cases [--target T ...] [--write DOC]`: the drive's protections
(fluxdrive.can.faultcases) injected on each target -- the C core's host build, the SIL
graph (`bench --sil`), the virtual board -- printed, or written into the generated table of
DOC (docs/firmware.md)."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from fluxdrive.can import faultcases as fc
from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import Parser


def main(argv: list[str] | None = None) -> int:
    ap = Parser(prog="fluxdrive fault-cases", description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument(
        "--target",
        action="append",
        choices=list(fc.TARGETS),
        help="run on this target (repeatable; default: all)",
    )
    ap.add_argument("--case", action="append", help="only this case (repeatable)")
    ap.add_argument("--write", type=Path, metavar="DOC", help="update the generated table in DOC")
    args = ap.parse_args(argv)
    try:
        cases = [fc.case(n) for n in args.case] if args.case else list(fc.CASES)
    except ValueError as exc:
        print(f"fault-cases: --case: {exc}", file=sys.stderr)
        return 2
    cells: dict[str, dict[str, str]] = {}
    bad = []
    for target in args.target or list(fc.TARGETS):
        todo = [c for c in cases if target not in c.not_on]
        t0 = time.perf_counter()
        if target == "sil":
            results = run_graph(todo, Path(tempfile.mkdtemp(prefix="fault-cases-")))[0]
        else:
            results = fc.run_in_process(todo, "c" if target == "core" else "pil")
        for c, res in zip(todo, results, strict=True):
            cells.setdefault(c.name, {})[target] = fc.cell(res)
            print(
                f"[fault-cases] {target} {c.name}: {fc.cell(res)} "
                f"{'ok' if res['ok'] else 'NOT MET: ' + str(res['checks'])}",
                file=sys.stderr,
            )
            if not res["ok"]:
                bad.append(f"{target} {c.name}")
        print(f"[fault-cases] {target}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    if args.write:
        fc.write_doc(args.write, cells)
        print(f"wrote the table into {args.write}", file=sys.stderr)
    else:
        print(fc.table(cells), end="")
    if bad:
        print(f"fault-cases: requirements not met: {', '.join(bad)}", file=sys.stderr)
        return 1
    return 0


def run_graph(
    cases: list[fc.FaultCase], work: Path, domain_id: int | None = None
) -> tuple[list[dict[str, Any]], list[Path]]:
    """The cases through the SIL graph (`bench --sil --inject`, subprocesses): one run with
    every case armed in the normal way, one after the other (the bench's operator resets and
    re-arms in between), and one run per case injected before arming. Their outcomes in
    the order of `cases`, and the bags."""
    import yaml

    ts = fc.fault_scenario(1.0).machine.ts_s
    got: dict[str, dict[str, Any]] = {}
    bags = []
    for i, run in enumerate(fc.runs_of(cases)):
        sp = work / f"fault_injection_{i}.yaml"
        sp.write_text(yaml.safe_dump(fc.scenario_raw(fc.run_drive_s(run, ts)), sort_keys=False))
        at = 0.0 if run[0].before_arming else fc.AT_S
        inject = ",".join([f"{run[0].name}@{at}", *(c.name for c in run[1:])])
        bag = work / f"bag_{i}"
        cmd = [sys.executable, "-m", "fluxdrive.cli", "bench", "--sil", str(sp), "--mode", "split",
               "--decimation", "4", "--bag", str(bag), "--quiet", "--inject", inject]  # fmt: skip
        if domain_id is not None:
            cmd += ["--domain-id", str(domain_id)]
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
        bags.append(bag)
        last = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
        try:
            outs = list(json.loads(last))
        except json.JSONDecodeError:
            why = (p.stdout + p.stderr).strip().splitlines()[-3:]
            outs = [{"case": c.name, "reaction": None, "bound": None, "level": " / ".join(why),
                     "ok": False, "checks": {"bench": False}} for c in run]  # fmt: skip
        got.update({r["case"]: r for r in outs})
    return [got[c.name] for c in cases], bags


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
