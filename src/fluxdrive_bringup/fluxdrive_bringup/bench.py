"""`./fluxdrive benchmark graph`: real-time factor of the lockstep graph against the
in-process runner, on the demo scenario (2 % speed / 150 % load: plant, four observers,
controller, recorder; every message recorded).

  lockstep_rtf    simulated time / wall time of the graph's lockstep loop (first frame to
                  last frame, as the plant measures it), 10 kHz PWM, composed layout;
                  the recorded bag is checked to hold every sample
  in_process_rtf  the same scenario and observers through fluxdrive.drive.sim.run_scenario

Options: --duration S (simulated seconds, default 3), --layouts composed,split,separate
(extra keys lockstep_rtf_<layout>), --repeat N (best of N).
Progress goes to stderr; the last line on stdout is a JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from fluxdrive.core.scenario import load_scenario, scenario_path


def _say(text: str) -> None:
    print(f"[bench graph] {text}", file=sys.stderr, flush=True)


def bench_graph(argv: list[str]) -> dict:
    from .runs import DEMO_SCENARIO, LAYOUTS, result_from_bag, run_graph, shorten

    ap = argparse.ArgumentParser(prog="fluxdrive benchmark graph", description=__doc__)
    ap.add_argument("--duration", type=float, default=3.0, help="simulated seconds (default 3)")
    ap.add_argument("--scenario", default=DEMO_SCENARIO)
    ap.add_argument("--layouts", default="composed",
                    help=f"comma-separated, of {','.join(LAYOUTS)} (first = lockstep_rtf)")
    ap.add_argument("--repeat", type=int, default=1, help="best of N graph runs per layout")
    ap.add_argument("--domain-id", type=int)
    args = ap.parse_args(argv)
    sp = scenario_path(args.scenario)
    layouts = [x.strip() for x in args.layouts.split(",") if x.strip()]
    for lay in layouts:
        if lay not in LAYOUTS:
            raise SystemExit(f"unknown layout {lay!r}; choose from {LAYOUTS}")

    # in-process reference (compiled kernels warmed up first)
    from fluxdrive.drive.sim import run_scenario

    sc = load_scenario(sp)
    shorten(sc, min(0.05, args.duration))
    _say("in-process: compiling / warming up ...")
    run_scenario(sc, progress=False)
    sc = load_scenario(sp)
    shorten(sc, args.duration)
    t0 = time.perf_counter()
    run_scenario(sc, progress=False)
    wall_ip = time.perf_counter() - t0
    in_rtf = sc.duration_s / wall_ip
    _say(f"in-process: {sc.n_periods} periods, {len(sc.observers)} observers in "
         f"{wall_ip:.2f} s = real-time factor {in_rtf:.2f}")

    out: dict = {}
    tmp = Path(tempfile.mkdtemp(prefix="fluxdrive-bench-"))
    try:
        for lay in layouts:
            best = None
            for rep in range(args.repeat):
                bag = tmp / f"bag-{lay}-{rep}"
                _say(f"graph ({lay}), run {rep + 1}/{args.repeat}: {args.duration:g} s "
                     f"simulated ...")
                r = run_graph(sp, out=tmp / f"run-{lay}-{rep}", bag=bag, layout=lay,
                              duration_s=args.duration, domain_id=args.domain_id, quiet=True,
                              timeout=600.0, progress=False)
                if r["code"] != 0 or r["lockstep_rtf"] is None:
                    raise RuntimeError(f"graph run ({lay}) failed (exit {r['code']}); logs in "
                                       f"{tmp / f'run-{lay}-{rep}' / 'logs'}")
                sc2 = load_scenario(sp)
                _, arr = result_from_bag(bag, sc2, args.duration)
                missing = sum(arr["missing"].values())
                _say(f"graph ({lay}): {r['frames']} frames in {r['loop_wall_s']:.2f} s = "
                     f"real-time factor {r['lockstep_rtf']:.3f}; bag: {arr['n']} frames, "
                     f"{missing} samples missing")
                if missing:
                    raise RuntimeError(f"graph run ({lay}) lost {missing} samples: "
                                       f"{arr['missing']}")
                best = r["lockstep_rtf"] if best is None else max(best, r["lockstep_rtf"])
                shutil.rmtree(bag, ignore_errors=True)
            out[f"lockstep_rtf_{lay}"] = round(best, 3)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res = {"lockstep_rtf": out[f"lockstep_rtf_{layouts[0]}"], "in_process_rtf": round(in_rtf, 2),
           "layout": layouts[0], "pwm_hz": sc.machine.pwm_hz, "observers": len(sc.observers),
           "simulated_s": args.duration, "recorded": True}
    if len(layouts) > 1:
        res.update(out)
    return res


def main(argv: list[str] | None = None) -> int:
    res = bench_graph(sys.argv[1:] if argv is None else argv)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
