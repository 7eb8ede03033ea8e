"""`./fluxdrive benchmark KIND`, KIND one of engine|replay|graph|paced|can|study|firmware|plugin|
bench|experiments|setup|services: throughput figures; the last line of each is a JSON object."""

from __future__ import annotations

import importlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.core.schema import Parser

# kind -> (module, function); each returns a dict printed as the JSON last line
BENCHES = {
    "engine": ("fluxdrive.cli.bench", "bench_engine"),
    "replay": ("fluxdrive.replay.lab", "bench_replay"),
    "graph": ("fluxdrive_bringup.measure.bench", "bench_graph"),
    "paced": ("fluxdrive_bringup.measure.bench", "bench_paced"),
    "can": ("fluxdrive.can.benchmark", "bench_can_cli"),
    "study": ("fluxdrive.study.cli", "bench_study"),
    "firmware": ("fluxdrive.cli.bench", "bench_firmware"),
    "plugin": ("fluxdrive.cli.bench", "bench_plugin"),
    "bench": ("fluxdrive.cli.hostbench", "bench_bench"),
    "experiments": ("fluxdrive.cli.bench", "bench_experiments"),
    "setup": ("fluxdrive.cli.setupbench", "bench_setup"),
    "services": ("fluxdrive_bringup.measure.answers", "bench_services"),
}


def bench_firmware(argv: list[str]) -> dict[str, Any]:
    """`benchmark firmware`: the target build's figures (fluxdrive.can.firmware_target),
    then the board image measured in closed loop on the virtual board
    (fluxdrive.can.vboard_bench); one record, the board's under "board"."""
    from fluxdrive.can.firmware_target import bench_firmware as target
    from fluxdrive.can.vboard_bench import BOARD_RESULTS_PATH, board_benchmark
    from fluxdrive.core.paths import ROOT

    rec = target(argv)
    board = board_benchmark()
    b = board["size"]
    print(f"board   {board['board']}: flash {b['flash']} B, RAM {b['ram']} B")
    for mode in ("split_mode", "host_mode"):
        m = board[mode]
        print(
            f"board   {mode} (D={m['decimation']}) on the virtual board, closed loop: period "
            f"interrupt max {m['isr_instructions_max']} instructions, median "
            f"{m['isr_instructions_median']} over {m['periods']} periods; cycles worst "
            f"{m['cycles_lower_max']}..{m['cycles_upper_max']}, median "
            f"{m['cycles_lower_median']}..{m['cycles_upper_median']} (lower..upper bound) = "
            f"{m['percent_of_period_upper']} % of a period by the upper; stack high-water "
            f"{m['stack_high_water_bytes']} B"
        )
        print(
            f"board   {mode} background loop (CAN outside the interrupt), per pass over "
            f"{m['background_passes']}: max {m['background_instructions_max']} instructions, "
            f"cycles worst {m['background_cycles_lower_max']}.."
            f"{m['background_cycles_upper_max']}, median {m['background_cycles_lower_median']}"
            f"..{m['background_cycles_upper_median']} = "
            f"{m['background_percent_of_period_upper']} % of a period by the upper"
        )
    print(f"written {BOARD_RESULTS_PATH.relative_to(ROOT)}")
    rec["board"] = board
    return rec


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


def _experiments_args(argv: list[str]):
    """`benchmark experiments`'s options."""
    ap = Parser(prog="fluxdrive benchmark experiments")
    ap.add_argument("names", nargs="?", default="paper", help="experiments or a group (paper)")
    ap.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="dask workers (default: every core; 1: in-process, one after the other)",
    )
    ap.add_argument("--seeds", type=int, metavar="N", help="as `experiment --seeds`")
    ap.add_argument("--quick", action="store_true", help="the quick variants")
    ap.add_argument(
        "--write",
        action="store_true",
        help="also write results/benchmarks/experiments_NAMES.json",
    )
    return ap.parse_args(argv)


def bench_experiments(argv: list[str]) -> dict:
    """The experiments' cost, run as `./fluxdrive experiment` runs them (in-process engine,
    no ROS; on a local cluster of `--workers`, every experiment and seed at once): the wall
    time, the CPU time of this process and its workers, and where it goes: per experiment
    its runs, their simulated seconds and CPU seconds in the simulation and in the analysis
    (metrics and extractor, where the run ran), and this process's own share (judging,
    plots, the runner).  The kernels are compiled (or loaded from the cache) before the
    clock starts; the report goes to a scratch folder, results/experiments is left alone."""
    import tempfile

    from fluxdrive.experiments.claims import MIN_SEEDS
    from fluxdrive.experiments.registry import expand, experiments, run_experiments
    from fluxdrive.study.runner import runner_from_args
    from fluxdrive.study.tasks import warm_kernels

    args = _experiments_args(argv)
    names = expand(args.names)
    bad = [n for n in names if n not in experiments()]
    if bad:
        raise SystemExit(f"benchmark experiments: unknown {bad}; known: {', '.join(experiments())}")
    load0 = os.getloadavg()[0]
    w0 = time.perf_counter()
    warm_kernels()  # compiled (or loaded from the cache) before the clock starts
    warm_s = time.perf_counter() - w0
    runner = runner_from_args(None, args.workers)
    in_process = runner.client is None
    ledger: list[dict] = []
    runtime: dict[str, float] = {}
    failed: list[str] = []

    def done(n: str, res: dict) -> None:
        runtime[n] = res["runtime_s"]
        print(f"[bench] {n:14s} done at {time.perf_counter() - wall0:7.1f} s", file=sys.stderr)

    def fail(n: str, exc: Exception) -> dict:
        failed.append(f"{n}: {exc!r}")
        return {"runtime_s": 0.0, "claims": []}

    try:
        with tempfile.TemporaryDirectory() as tmp:
            wall0, cpu0, own0 = time.perf_counter(), _cpu_s(), time.process_time()
            run_experiments(
                names,
                Path(tmp) / "report",
                done,
                fail,
                runner,
                quick=args.quick,
                echo=False,
                seeds=args.seeds,
                ledger=ledger,
            )
            wall, cpu = time.perf_counter() - wall0, _cpu_s() - cpu0
            own = time.process_time() - own0
    finally:
        runner.close()
    if failed:
        raise SystemExit("benchmark experiments: " + "; ".join(failed))
    out = {
        "names": args.names,
        "total_wall_s": round(wall, 1),
        "total_cpu_s": round(cpu, 1),
        "workers": runner.workers,
        "seeds": args.seeds or (1 if args.quick else MIN_SEEDS),
        "quick": args.quick,
        "cpu_count": os.cpu_count(),
        "warm_s": round(warm_s, 1),
        "load_average_1min_at_start": round(load0, 2),
        **run_costs(ledger, names, runtime, own, in_process),
    }
    print(
        f"[bench] {len(names)} experiments: {wall:.1f} s wall, {cpu:.1f} s CPU "
        f"({out['runs']} runs: {out['cpu_run_s']:.1f} s simulating, "
        f"{out['cpu_analysis_s']:.1f} s analysing; this process {out['own_cpu_s']:.1f} s)",
        file=sys.stderr,
    )
    if args.write:
        label = args.names.replace(",", "_") + ("_quick" if args.quick else "")
        write_benchmark(f"experiments_{label}", out)
    return out


def run_costs(
    ledger: list[dict],
    names: list[str],
    runtime: dict[str, float],
    own_cpu_s: float,
    in_process: bool,
) -> dict:
    """The ledger of runs (Ctx.ledger) summed: over all and per experiment, runs, simulated
    seconds, CPU seconds simulating and analysing; this process's own CPU seconds
    (`own_cpu_s`, less the runs' when they ran `in_process`)."""

    def total(rows: list[dict]) -> dict:
        return {
            "runs": len(rows),
            "sim_s": round(sum(r["sim_s"] for r in rows), 1),
            "cpu_run_s": round(sum(r["cpu_run_s"] for r in rows), 2),
            "cpu_analysis_s": round(sum(r["cpu_analysis_s"] for r in rows), 2),
        }

    per = {n: total([r for r in ledger if r["experiment"] == n]) for n in names}
    for n in names:
        per[n]["cpu_s"] = round(per[n]["cpu_run_s"] + per[n]["cpu_analysis_s"], 2)
        per[n]["runtime_s"] = runtime.get(n, math.nan)
    out = total(ledger)
    if in_process:
        own_cpu_s = max(own_cpu_s - out["cpu_run_s"] - out["cpu_analysis_s"], 0.0)
    return {**out, "own_cpu_s": round(own_cpu_s, 1), "experiments": per}


def _engine_cases() -> tuple[Path, Any, Any]:
    """The engine benchmark's cases: the shipped 2 %/150 % scenario with the driving flux
    observer and one shadow (EMF, commanded voltages) on its non-ideal bench (the paper
    bench) and on the ideal bench.  Returns (scenario file, paper case, ideal case)."""
    from fluxdrive.drive.observers import observer_config
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario

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
    return path, sc, ideal


def _engine_warm(path: Path, sc: Any, ideal: Any) -> float:
    """Compile (or load from the cache) every kernel of both cases with a 50 ms run of
    each; returns the wall seconds that took."""
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.drive.sim import run_scenario

    t0 = time.perf_counter()
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
    return time.perf_counter() - t0


def engine_runs(reps: int = 3) -> dict:
    """The engine benchmark in this interpreter, on whichever `fluxdrive` it imports: warm
    up, then `reps` runs of each case, alternating (so both see the same machine load).
    Returns the best periods per wall second and per process-CPU second of each case
    ("paper_bench", "ideal_bench"), the warm-up's wall seconds and the engine's folder."""
    import fluxdrive
    from fluxdrive.drive.sim import run_scenario

    path, sc, ideal = _engine_cases()
    print("[bench] compiling / warming up ...", file=sys.stderr)
    warm_s = _engine_warm(path, sc, ideal)
    wall = {"paper_bench": 0.0, "ideal_bench": 0.0}
    cpu = dict(wall)
    for rep in range(reps):
        for key, case in (("paper_bench", sc), ("ideal_bench", ideal)):
            t0, c0 = time.perf_counter(), time.process_time()
            res = run_scenario(case, progress=False)
            dt, dc = time.perf_counter() - t0, time.process_time() - c0
            rate = case.n_periods / dt
            print(
                f"[bench] run {rep + 1}/{reps} ({key.replace('_', ' ')}): {case.n_periods} "
                f"periods in {dt:.3f} s = {rate / 1e3:.0f} k periods/s, "
                f"{case.duration_s / dt:.1f}x real time ({case.n_periods / dc / 1e3:.0f} k "
                f"per CPU second)",
                file=sys.stderr,
            )
            wall[key] = max(wall[key], rate)
            cpu[key] = max(cpu[key], case.n_periods / dc)
            del res
    return {
        "periods_per_wall_s": wall,
        "periods_per_cpu_s": cpu,
        "warm_s": round(warm_s, 2),
        "ts_s": sc.machine.ts_s,
        "scenario": sc.name,
        "engine": str(Path(fluxdrive.__file__).resolve().parent),
    }


def bench_engine(argv: list[str]) -> dict:
    """Closed loop in-process: switching-level plant + driving observer + one shadow + FOC,
    on the shipped scenario's non-ideal bench and on the ideal bench (runs alternate, so
    both see the same machine load; best of 3 each).  `--against REF`: this checkout's
    engine against commit REF's, measured alternately in fresh interpreters
    (`bench_engine_against`)."""

    ap = Parser(prog="fluxdrive benchmark engine")
    ap.add_argument("--against", metavar="REF", help="a commit to measure this engine against")
    ap.add_argument("--rounds", type=int, default=3, help="--against: rounds (default 3)")
    ap.add_argument(
        "--write",
        action="store_true",
        help="--against: write results/benchmarks/engine_against.json",
    )
    args = ap.parse_args(argv)
    if args.against is not None:
        return bench_engine_against(args.against, args.rounds, args.write)
    if args.write or args.rounds != 3:
        raise SystemExit("benchmark engine: --rounds and --write go with --against REF")
    runs = engine_runs(3)
    best, ts = runs["periods_per_wall_s"], runs["ts_s"]
    return {
        "periods_per_s": round(best["paper_bench"]),
        "real_time_factor": round(best["paper_bench"] * ts, 2),
        "ideal_bench_periods_per_s": round(best["ideal_bench"]),
        "ideal_bench_real_time_factor": round(best["ideal_bench"] * ts, 2),
        "observers": 2,
        "plant": "switching-level",
        "scenario": runs["scenario"],
    }


# a child of `bench_engine_against`: the engine of the tree whose python/ it puts first on
# sys.path, driven by this file's `engine_serve`, loaded by its path (not as a module of that
# engine), so both engines are measured by the same code
_CHILD = (
    "import runpy, sys\n"
    "sys.path.insert(0, sys.argv[1])\n"
    "runpy.run_path(sys.argv[2])['engine_serve']()\n"
)
RUNS_PER_ROUND = 3
ENGINE_CASES = ("paper_bench", "ideal_bench")
SIDES = ("ref", "checkout")


def engine_serve() -> None:
    """The engine benchmark one step at a time, on whichever `fluxdrive` this interpreter
    imports: a command a line on stdin, a JSON line back with the step's wall and
    process-CPU seconds.  `warm`: compile or load every kernel (answers the engine's
    folder and each case's periods); `start CASE`: a fresh run of case CASE set up as
    `run_scenario` sets it up; `chunk`: its next 0.25 s (`run_scenario`'s chunk; answers
    `done` after the last); anything else ends."""
    import fluxdrive
    from fluxdrive.drive.sim import DriveSetup, LoopRun

    path, sc, ideal = _engine_cases()
    cases = dict(zip(ENGINE_CASES, (sc, ideal), strict=True))
    run, chunk = None, 1
    for line in sys.stdin:
        cmd, _, arg = line.strip().partition(" ")
        t0, c0 = time.perf_counter(), time.process_time()
        info: dict[str, Any] = {}
        if cmd == "warm":
            _engine_warm(path, sc, ideal)
            info["engine"] = str(Path(fluxdrive.__file__).resolve().parent)
            info["periods"] = {k: c.n_periods for k, c in cases.items()}
        elif cmd == "start":
            run = LoopRun(DriveSetup(cases[arg]))
            run.advance(0)
            chunk = max(1, int(0.25 / run.ds.ts))
        elif cmd == "chunk" and run is not None:
            run.advance(min(run.n, run.k + chunk))
            info["done"] = run.k >= run.n
            if info["done"]:
                run.result()
        else:
            return
        info.update(wall=time.perf_counter() - t0, cpu=time.process_time() - c0)
        print(json.dumps(info), flush=True)


class _EngineChild:
    """`engine_serve` in a fresh interpreter of this venv on the engine of checkout `tree`
    (its python/ first on sys.path, its config, numba cache folder `cache`)."""

    def __init__(self, side: str, tree: Path, cache: Path, log: Path):
        import subprocess

        self.side, self.tree, self.log = side, tree, log
        env = {**os.environ, "FLUXDRIVE_ROOT": str(tree), "NUMBA_CACHE_DIR": str(cache)}
        args = [sys.executable, "-c", _CHILD, str(tree / "python"), __file__]
        with open(log, "w") as err:
            self.proc = subprocess.Popen(
                args,
                cwd=tree,
                env=env,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )

    def ask(self, cmd: str) -> dict:
        """Send one command, return its answer; SystemExit naming the child if it died."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        try:
            self.proc.stdin.write(cmd + "\n")
            self.proc.stdin.flush()
            line = self.proc.stdout.readline()
        except OSError:
            line = ""
        if not line:
            lines = self.log.read_text(errors="replace").strip().splitlines()
            raise SystemExit(
                f"benchmark engine: the {self.side} engine ({self.tree}) failed: "
                f"{lines[-1] if lines else 'no message'}"
            )
        return json.loads(line)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.ask_quietly("quit")
            self.proc.wait(timeout=60)

    def ask_quietly(self, cmd: str) -> None:
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(cmd + "\n")
            self.proc.stdin.flush()
        except OSError:
            pass


def _lockstep_round(kids: dict[str, _EngineChild], r: int) -> dict:
    """One round: RUNS_PER_ROUND runs of each case on both engines at once, chunk by chunk
    in turn (the first to step alternates run by run), so a change of the machine's load
    meets both.  Returns {side: {case: [[(cpu, wall) per step] per run]}}."""
    steps: dict[str, dict[str, list]] = {s: {c: [] for c in ENGINE_CASES} for s in kids}
    for rep in range(RUNS_PER_ROUND):
        for i, case in enumerate(ENGINE_CASES):
            order = list(kids) if (rep + i + r) % 2 == 0 else list(kids)[::-1]
            for s in order:
                a = kids[s].ask(f"start {case}")
                steps[s][case].append([(a["cpu"], a["wall"])])
            done = False
            while not done:
                answers = {s: kids[s].ask("chunk") for s in order}
                for s, a in answers.items():
                    steps[s][case][-1].append((a["cpu"], a["wall"]))
                done = all(a["done"] for a in answers.values())
                if any(a["done"] for a in answers.values()) and not done:
                    raise SystemExit("benchmark engine: the two engines' runs differ in length")
    return steps


def _ref_commit(ref: str, root: Path) -> str:
    """The full hash of commit `ref` of the checkout at `root`, which must hold the
    in-process engine; else SystemExit with one line."""
    import subprocess

    bad = f"benchmark engine: --against {ref}:"
    if not ref or ref.startswith("-"):
        raise SystemExit(f"{bad} not a commit name")
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=30,
        ).stdout.strip()
        has_engine = (
            sha
            and not subprocess.run(
                ["git", "cat-file", "-e", f"{sha}:python/fluxdrive/drive/sim.py"],
                cwd=root,
                capture_output=True,
                timeout=30,
            ).returncode
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise SystemExit(f"{bad} git could not read the checkout {root}: {exc}") from None
    if not sha:
        raise SystemExit(f"{bad} no such commit in the checkout {root}")
    if not has_engine:
        raise SystemExit(f"{bad} commit {sha[:10]} has no python/fluxdrive/drive/sim.py")
    return sha


def _export_commit(sha: str, root: Path, dest: Path) -> None:
    """The tree of commit `sha` (git archive) into the folder `dest`."""
    import io
    import subprocess
    import tarfile

    tar = subprocess.run(["git", "archive", "--format=tar", sha], cwd=root, capture_output=True)
    if tar.returncode:
        msg = tar.stderr.decode(errors="replace").strip().splitlines()
        raise SystemExit(f"benchmark engine: git archive {sha[:10]} failed: {msg[-1:]}")
    with tarfile.open(fileobj=io.BytesIO(tar.stdout)) as tf:
        tf.extractall(dest, filter="data")


def bench_engine_against(ref: str, rounds: int, write: bool) -> dict:
    """This checkout's engine against commit REF's (exported with git archive into a
    temporary folder), measured by the same code (`engine_serve`): each round starts both
    in fresh interpreters of this venv, each with a numba cache of its own, new (so the
    first round's warm-up is a cold compile), and runs them in lockstep
    (`_lockstep_round`).  Ratios are this engine's speed over REF's."""
    import tempfile

    from fluxdrive.core.paths import ROOT

    if rounds < 1:
        raise SystemExit(f"benchmark engine: --rounds {rounds}: at least 1")
    sha = _ref_commit(ref, ROOT)
    commit = _checkout_commit()  # before: an edit while it runs shows as -dirty
    steps: dict[str, dict[str, list]] = {s: {c: [] for c in ENGINE_CASES} for s in SIDES}
    warm: dict[str, list[float]] = {s: [] for s in SIDES}
    loads, periods = [], {}
    with tempfile.TemporaryDirectory(prefix="fluxdrive-against-") as tmp:
        base = Path(tmp)
        _export_commit(sha, ROOT, base / "tree")
        where = {"ref": base / "tree", "checkout": ROOT}
        for r in range(rounds):
            loads.append(round(os.getloadavg()[0], 2))
            print(f"[bench] round {r + 1}/{rounds} (load {loads[-1]})", file=sys.stderr)
            kids = {
                s: _EngineChild(s, where[s], base / f"numba-{s}", base / f"{s}.log") for s in SIDES
            }
            try:
                for s, kid in kids.items():  # one at a time: the first round's compile times
                    a = kid.ask("warm")
                    if Path(a["engine"]) != (where[s] / "python" / "fluxdrive").resolve():
                        raise SystemExit(f"benchmark engine: the {s} child ran {a['engine']}")
                    warm[s].append(round(a["wall"], 2))
                    periods = a["periods"]
                got = _lockstep_round(kids, r)
            finally:
                for kid in kids.values():
                    kid.close()
            for s in SIDES:
                for c in ENGINE_CASES:
                    steps[s][c] += got[s][c]
    out = _against_summary(steps, periods)
    out.update(
        against=ref,
        against_commit=sha[:10],
        commit=commit,
        rounds=rounds,
        runs_per_round=RUNS_PER_ROUND,
        warm_s=warm,
        load_average_1min_per_round=loads,
        method="both engines at once, 0.25 s chunks in turn; ratio: the median over the "
        "chunks of REF's time over this engine's",
    )
    if write:
        write_benchmark("engine_against", out)
    return out


def _checkout_commit() -> str:
    from fluxdrive.study.cli import _commit

    return _commit()


def _against_summary(steps: dict[str, dict[str, list]], periods: dict[str, int]) -> dict:
    """Per case and clock (process CPU, wall): this engine's speed over REF's as the median
    of the chunks' ratios (REF's time over this engine's for the same chunk of the same
    run, measured side by side: robust to a burst of load on one of them), each engine's
    best run in periods per second and their ratio, and the ratio run by run (CPU).
    Prints the table."""
    out: dict[str, Any] = {}
    head = f"{'REF k/s':>9s} {'this k/s':>9s} {'best':>7s} {'median chunk':>12s}"
    print(f"[bench] {'':12s} {'clock':5s} {head}", file=sys.stderr)
    for case in ENGINE_CASES:
        ref, new = steps["ref"][case], steps["checkout"][case]
        for k, clock in enumerate(("cpu", "wall")):
            t_ref = [sum(st[k] for st in run) for run in ref]
            t_new = [sum(st[k] for st in run) for run in new]
            chunks = [
                a[k] / b[k]
                for ra, rb in zip(ref, new, strict=True)
                for a, b in zip(ra, rb, strict=True)
                if b[k] > 0
            ]
            med = float(np.median(chunks))
            best_ref, best_new = periods[case] / min(t_ref), periods[case] / min(t_new)
            out[f"{case}_ratio_per_{clock}_s"] = round(med, 4)
            out[f"{case}_best_ratio_per_{clock}_s"] = round(best_new / best_ref, 4)
            out[f"{case}_ref_periods_per_{clock}_s"] = round(best_ref)
            out[f"{case}_periods_per_{clock}_s"] = round(best_new)
            if clock == "cpu":
                out[f"{case}_run_ratios_per_cpu_s"] = [
                    round(a / b, 4) for a, b in zip(t_ref, t_new, strict=True)
                ]
            print(
                f"[bench] {case.replace('_', ' '):12s} {clock:5s} {best_ref / 1e3:9.1f} "
                f"{best_new / 1e3:9.1f} {best_new / best_ref:7.4f} {med:12.4f}",
                file=sys.stderr,
            )
    return out


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

    from fluxdrive.drive.observers import make_observer
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive.io.bagio import read_run_bag
    from fluxdrive.replay.lab import SAMPLES_DIR, parse_variant

    ap = Parser(prog="fluxdrive benchmark plugin")
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
