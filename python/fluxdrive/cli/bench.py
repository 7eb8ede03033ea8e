"""`./fluxdrive benchmark engine|replay|graph|paced|can|study|firmware|plugin|bench|experiments`:
throughput figures; the last line of each is a JSON object."""

from __future__ import annotations

import importlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

# kind -> (module, function); each returns a dict printed as the JSON last line
BENCHES = {
    "engine": ("fluxdrive.cli.bench", "bench_engine"),
    "replay": ("fluxdrive.replay.lab", "bench_replay"),
    "graph": ("fluxdrive_bringup.measure.bench", "bench_graph"),
    "paced": ("fluxdrive_bringup.measure.bench", "bench_paced"),
    "can": ("fluxdrive.can.benchmark", "bench_can_cli"),
    "study": ("fluxdrive.study.cli", "bench_study"),
    "firmware": ("fluxdrive.can.firmware_target", "bench_firmware"),
    "plugin": ("fluxdrive.cli.bench", "bench_plugin"),
    "bench": ("fluxdrive.cli.hostbench", "bench_bench"),
    "experiments": ("fluxdrive.cli.bench", "bench_experiments"),
}


def benchmark_path(name: str) -> Path:
    """results/benchmarks/<name>.json: the file the docs quote."""
    from fluxdrive.core.paths import ROOT

    return ROOT / "results" / "benchmarks" / f"{name}.json"


def stamped(res: dict) -> dict:
    """`res` with when it was measured and how loaded the machine was."""
    return {
        **res,
        "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
    }


def write_benchmark(name: str, res: dict) -> Path:
    """results/benchmarks/<name>.json (the file the docs quote), stamped."""
    path = benchmark_path(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(stamped(res), indent=1, sort_keys=True) + "\n")
    print(f"[bench] wrote {path}", file=sys.stderr)
    return path


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and of its live child processes (the
    dask workers of a local cluster)."""
    import psutil

    me = psutil.Process()
    total = sum(me.cpu_times()[:2])
    for ch in me.children(recursive=True):
        try:
            total += sum(ch.cpu_times()[:2])
        except psutil.Error:  # a worker that ended between listing and reading
            pass
    return total


def bench_experiments(argv: list[str]) -> dict:
    """The experiments' cost: each one run as `./fluxdrive experiment` runs it (in-process
    engine, no ROS), its wall time and the CPU time it took (this process and its workers);
    the report goes to a scratch folder, results/experiments is left alone."""
    import argparse
    import tempfile

    from fluxdrive.experiments.registry import expand, experiments, run_experiment
    from fluxdrive.study.runner import runner_from_args
    from fluxdrive.study.tasks import warm_kernels

    ap = argparse.ArgumentParser(prog="fluxdrive benchmark experiments")
    ap.add_argument("names", nargs="?", default="paper", help="experiments or a group (paper)")
    ap.add_argument("--workers", type=int, default=1, help="dask workers (1: in-process)")
    ap.add_argument("--quick", action="store_true", help="the quick variants")
    ap.add_argument(
        "--write", action="store_true", help="also write results/benchmarks/experiments.json"
    )
    args = ap.parse_args(argv)
    names = expand(args.names)
    bad = [n for n in names if n not in experiments()]
    if bad:
        raise SystemExit(f"benchmark experiments: unknown {bad}; known: {', '.join(experiments())}")
    warm_kernels()  # compiled (or loaded from the cache) before the clock starts
    runner = runner_from_args(None, args.workers)
    per: dict[str, dict] = {}
    try:
        with tempfile.TemporaryDirectory() as tmp:
            wall0, cpu0 = time.perf_counter(), _cpu_s()
            for n in names:
                w, c = time.perf_counter(), _cpu_s()
                run_experiment(n, Path(tmp) / "report", args.quick, runner, echo=False)
                per[n] = {
                    "wall_s": round(time.perf_counter() - w, 2),
                    "cpu_s": round(_cpu_s() - c, 2),
                }
                print(
                    f"[bench] {n:14s} {per[n]['wall_s']:7.1f} s wall {per[n]['cpu_s']:7.1f} s CPU",
                    file=sys.stderr,
                )
            wall, cpu = time.perf_counter() - wall0, _cpu_s() - cpu0
    finally:
        runner.close()
    print(f"[bench] {len(names)} experiments: {wall:.1f} s wall, {cpu:.1f} s CPU", file=sys.stderr)
    out = {
        "names": args.names,
        "experiments": per,
        "total_wall_s": round(wall, 1),
        "total_cpu_s": round(cpu, 1),
        "workers": args.workers,
        "quick": args.quick,
        "cpu_count": os.cpu_count(),
    }
    if args.write:
        label = args.names.replace(",", "_") + ("_quick" if args.quick else "")
        write_benchmark(f"experiments_{label}", out)
    return out


def bench_engine(argv: list[str]) -> dict:
    """Closed loop in-process: switching-level plant + driving observer + one shadow + FOC,
    on the shipped scenario's non-ideal bench and on the ideal bench (runs alternate, so
    both see the same machine load; best of 3 each)."""
    from fluxdrive.drive.observers import observer_config
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
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


EXAMPLE_PLUGIN = "my_observer.flux_pll:FluxPllObserver"


def _importable_example(spec: str) -> None:
    """The shipped example (examples/my_observer) without installing it."""
    from fluxdrive.drive.scenario import REPO_ROOT

    if spec.split(":")[0].split(".")[0] == "my_observer":
        path = str(REPO_ROOT / "examples" / "my_observer")
        if path not in sys.path:
            sys.path.insert(0, path)


def _plugin_case(spec: str, kwargs: dict, driving: str, seconds: float):
    """The 2 %/150 % scenario cut to `seconds`, the ideal bench, one observer: `driving`
    'user' (the plugin) or 'kernel' (paper_robust)."""
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario

    obs = (
        {"user": {"variant": spec, "extra": kwargs}}
        if driving == "user"
        else {"kernel": {"variant": "paper_robust"}}
    )
    return load_scenario(
        CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml",
        overrides={
            "bench": {},
            "duration_s": seconds,
            "steady_window_s": [0.0, seconds],
            "observers": obs,
            "driving": driving,
        },
    )


def bench_plugin(argv: list[str]) -> dict:
    """What a user variant (a Python class) costs per sample: its run() over recorded
    frames (replay; the base class loops over step()), and a closed loop it drives
    in-process (the per-period Python loop, step() per frame) against the built-in flux
    observer (paper_robust) in the compiled loop.  Costs are this process's CPU time (best
    of 3), which a loaded machine hardly changes; wall time would."""
    import argparse

    from fluxdrive.drive.observers import make_observer
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive.io.bagio import read_run_bag
    from fluxdrive.replay.lab import SAMPLES_DIR, parse_variant

    ap = argparse.ArgumentParser(prog="fluxdrive benchmark plugin")
    ap.add_argument("spec", nargs="?", default=EXAMPLE_PLUGIN, help="module:Class[:k=v,...]")
    ap.add_argument("--samples", type=int, default=100_000, help="replay: frames stepped")
    ap.add_argument("--seconds", type=float, default=1.0, help="closed loop: simulated time")
    ap.add_argument("--write", action="store_true", help="also write results/benchmarks/LABEL.json")
    ap.add_argument("--label", default="plugin_observer", help="the results file's name")
    args = ap.parse_args(argv)
    vs = parse_variant(args.spec)
    target, kwargs = vs.target, vs.params
    _importable_example(target)
    bag = read_run_bag(SAMPLES_DIR / "paper_2pct_150load")
    card = bag.machine()
    reps = max(1, args.samples // bag.n)
    frames = np.ascontiguousarray(np.tile(bag.frames, (reps, 1))[: args.samples])
    frames[:, FR_SEQ] = np.arange(len(frames), dtype=float)
    replay_us = {}
    for label, spec in (("user", target), ("kernel", "paper_robust")):
        obs = make_observer(spec, card, **(kwargs if label == "user" else {}))
        obs.run(frames[:16])  # import / compile
        best = math.inf
        for _ in range(3):
            obs.reset()
            t0 = time.process_time()
            obs.run(frames)
            best = min(best, (time.process_time() - t0) / len(frames))
        replay_us[label] = best * 1e6
        print(f"[bench] replay {label:6s} {spec}: {best * 1e6:8.3f} us/sample", file=sys.stderr)
    loop_us = {}
    for label in ("user", "kernel"):
        sc = _plugin_case(target, kwargs, label, args.seconds)
        warm = _plugin_case(target, kwargs, label, 0.01)
        run_scenario(warm, progress=False)
        best = math.inf
        for _ in range(3):
            t0 = time.process_time()
            run_scenario(sc, progress=False)
            best = min(best, (time.process_time() - t0) / sc.n_periods)
        loop_us[label] = best * 1e6
        print(
            f"[bench] closed loop, {label} observer driving: {best * 1e6:8.2f} us/period "
            f"({card.ts_s / best:.2f}x real time)",
            file=sys.stderr,
        )
    out = {
        "plugin": target,
        "plugin_kwargs": kwargs,
        "replay_us_per_sample": round(replay_us["user"], 3),
        "kernel_replay_us_per_sample": round(replay_us["kernel"], 4),
        "closed_loop_us_per_period": round(loop_us["user"], 2),
        "kernel_closed_loop_us_per_period": round(loop_us["kernel"], 2),
        "closed_loop_real_time_factor": round(card.ts_s * 1e6 / loop_us["user"], 3),
        "pwm_period_us": round(card.ts_s * 1e6, 3),
        "samples": len(frames),
        "closed_loop_s": args.seconds,
        "clock": "process CPU time",
    }
    if args.write:
        write_benchmark(args.label, out)
    return out


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in BENCHES:
        print(f"usage: fluxdrive benchmark {{{'|'.join(BENCHES)}}}", file=sys.stderr)
        return 2
    mod, fn = BENCHES[argv[0]]
    func = getattr(importlib.import_module(mod), fn)
    out = func(argv[1:])
    print(json.dumps(out, default=lambda x: float(x) if isinstance(x, np.floating) else str(x)))
    return 0
