"""`./fluxdrive sim SCENARIO.yaml [--out DIR]`: a scenario headless, in-process."""

from __future__ import annotations

import time
from pathlib import Path

from fluxdrive.analysis.report import report
from fluxdrive.core.schema import Parser
from fluxdrive.drive.scenario import MACHINE_HELP, REPO_ROOT, load_scenario, scenario_path
from fluxdrive.drive.sim import run_scenario


def main_sim(argv: list[str]) -> int:
    ap = Parser(prog="fluxdrive sim", description=__doc__)
    ap.add_argument("scenario", help="scenario YAML (path, or a name under config/scenarios)")
    ap.add_argument("--out", type=Path, help="output folder (default runs/<name>-sim-<time>)")
    ap.add_argument("--machine", help=MACHINE_HELP)
    ap.add_argument("--no-plots", action="store_true")
    args = ap.parse_args(argv)
    sc = load_scenario(scenario_path(args.scenario), machine=args.machine)
    if sc.machine_note:
        print(sc.machine_note, flush=True)
    out = args.out or REPO_ROOT / "runs" / f"{sc.name}-sim-{time.strftime('%Y%m%d-%H%M%S')}"
    res = run_scenario(sc, progress="always")
    rtf = sc.duration_s / res.wall_s if res.wall_s > 0 else float("inf")
    print(
        f"simulated {sc.duration_s:.2f} s ({sc.n_periods} PWM periods, "
        f"{len(res.names)} observers) in {res.wall_s:.2f} s wall: {rtf:.1f}x real time"
    )
    m = report(res, out, plots=not args.no_plots)
    return 0 if m["stable"] else 1
