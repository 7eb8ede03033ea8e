"""`./fluxdrive benchmark engine|replay|graph|paced|can|study|firmware`: throughput figures;
the last line of each is a JSON object."""

from __future__ import annotations

import importlib
import json
import sys
import time

import numpy as np

# kind -> (module, function); each returns a dict printed as the JSON last line
BENCHES = {
    "engine": ("fluxdrive.cli.bench", "bench_engine"),
    "replay": ("fluxdrive.replay.lab", "bench_replay"),
    "graph": ("fluxdrive_bringup.bench", "bench_graph"),
    "paced": ("fluxdrive_bringup.bench", "bench_paced"),
    "can": ("fluxdrive.can.benchmark", "bench_can_cli"),
    "study": ("fluxdrive.study.cli", "bench_study"),
    "firmware": ("fluxdrive.can.firmware_target", "bench_firmware"),
}


def bench_engine(argv: list[str]) -> dict:
    """Closed loop in-process: switching-level plant + driving observer + one shadow + FOC,
    on the shipped scenario's non-ideal bench and on the ideal bench (runs alternate, so
    both see the same machine load; best of 3 each)."""
    from fluxdrive.core.scenario import CONFIG_DIR, load_scenario
    from fluxdrive.drive.observers import observer_config
    from fluxdrive.drive.sim import run_scenario

    path = CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml"
    sc = load_scenario(path)
    sc.observers = {
        "flux_measured": sc.observers["flux_measured"],
        "emf_commanded": sc.bench.apply_observer_model(
            observer_config("emf", voltage_source="commanded"), sc.machine
        ),
    }
    ideal = load_scenario(path, overrides={"bench": {}})
    ideal.observers = {
        "flux_measured": ideal.observers["flux_measured"],
        "emf_commanded": observer_config("emf", voltage_source="commanded"),
    }
    print("[bench] compiling / warming up ...", file=sys.stderr)
    for base in (sc, ideal):
        warm = load_scenario(
            path,
            overrides={
                "duration_s": 0.05,
                "steady_window_s": [0.0, 0.05],
                **({} if base is sc else {"bench": {}}),
            },
        )
        warm.observers = base.observers
        run_scenario(warm, progress=False)
    best = {"bench": 0.0, "ideal": 0.0}
    for rep in range(3):
        for key, case in (("bench", sc), ("ideal", ideal)):
            t0 = time.perf_counter()
            res = run_scenario(case, progress=False)
            dt = time.perf_counter() - t0
            rate = case.n_periods / dt
            print(
                f"[bench] run {rep + 1}/3 ({key} bench): {case.n_periods} periods in "
                f"{dt:.3f} s = {rate / 1e3:.0f} k periods/s, {case.duration_s / dt:.1f}x real "
                f"time",
                file=sys.stderr,
            )
            best[key] = max(best[key], rate)
            del res
    ts = sc.machine.ts_s
    return {
        "periods_per_s": round(best["bench"]),
        "real_time_factor": round(best["bench"] * ts, 2),
        "ideal_bench_periods_per_s": round(best["ideal"]),
        "ideal_bench_real_time_factor": round(best["ideal"] * ts, 2),
        "observers": 2,
        "plant": "switching-level",
        "scenario": sc.name,
    }


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in BENCHES:
        print(f"usage: fluxdrive benchmark {{{'|'.join(BENCHES)}}}", file=sys.stderr)
        return 2
    mod, fn = BENCHES[argv[0]]
    func = getattr(importlib.import_module(mod), fn)
    out = func(argv[1:])
    print(json.dumps(out, default=lambda x: float(x) if isinstance(x, np.floating) else str(x)))
    return 0
