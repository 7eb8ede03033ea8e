"""`./fluxdrive benchmark services`: how long the drive's services take to answer, with the
services on a thread of their own (fluxdrive_ros.services, the default) and on the data
path's executor (`FLUXDRIVE_SERVICE_THREAD=0`), on a quiet machine and beside busy processes.

For each of the two settings one composed lockstep graph of the scenario runs (plant,
observers, controller in one process, no recorder).  Once it is in its run phase an operator
session (the node `./fluxdrive fault reset` uses) calls, one after the other, --calls times
each:

  get    /controller/get_parameters   position_timeout_s (answered on the service thread)
  set    /controller/set_parameters   position_timeout_s, alternating between two values
         (a change: runs on the data path between two callbacks)
  reset  /controller/reset_fault      (runs on the data path; "no latched fault" or a
         cleared latch, either is an answer)

first quiet, then with --busy busy processes beside it (default 2: with the graph's loop and
the caller, about twice the two cores).  Each call's answer time is the wall time of the
client's call (`inspect.commands._call`, which sends a request again after 1 s without an
answer), p50/p99/max per call and phase; a call with no answer within 5 s counts as
unanswered.  runnable_mean: the mean number of runnable tasks on the machine during the
phase (/proc/loadavg, sampled), the load the answers were measured at.

Progress goes to stderr; the last line on stdout is a JSON object.  --write stores it in
results/benchmarks/services.json (quoted by docs/graph.md and docs/safety.md).
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from fluxdrive.cli.bench import write_benchmark
from fluxdrive.core.schema import Parser, option
from fluxdrive.io.graphfile import GraphSettings

CALLS = ("get", "set", "reset")
PHASES = ("quiet", "busy")
SETTINGS = {"thread": "1", "data_path": "0"}  # key -> FLUXDRIVE_SERVICE_THREAD
PARAM = "position_timeout_s"
PARAM_VALUES = (0.05, 0.06)
CALL_TIMEOUT_S = 5.0
BUSY = "while True:\n    pass\n"


def _say(text: str) -> None:
    print(f"[bench services] {text}", file=sys.stderr, flush=True)


def _parser() -> Parser:
    from fluxdrive_bringup.launch.runs import DEMO_SCENARIO

    ap = Parser(prog="fluxdrive benchmark services", description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default=DEMO_SCENARIO, help="scenario name or path")
    ap.add_argument("--calls", type=int, default=100, help="calls of each kind per phase")
    ap.add_argument("--busy", type=int, default=2, help="busy processes in the busy phase")
    option(ap, "--domain-id", GraphSettings, help="ROS domain (default: a free one)")
    ap.add_argument(
        "--write", action="store_true", help="also write results/benchmarks/services.json"
    )
    return ap


def bench_services(argv: list[str]) -> dict:
    args = _parser().parse_args(argv)
    if not 1 <= args.calls <= 10_000:
        raise SystemExit(f"benchmark services: --calls must be in [1, 10000], got {args.calls}")
    if not 0 <= args.busy <= 64:
        raise SystemExit(f"benchmark services: --busy must be in [0, 64], got {args.busy}")
    from fluxdrive.drive.scenario import load_scenario, scenario_path

    from fluxdrive_bringup.launch.domains import pick_domain_id

    sp = scenario_path(args.scenario)
    sc = load_scenario(sp)
    dom = args.domain_id if args.domain_id is not None else pick_domain_id()
    res: dict = {
        "scenario": sp.stem,
        "calls_per_phase": args.calls,
        "busy_processes": args.busy,
        "cores": os.cpu_count(),
    }
    tmp = Path(tempfile.mkdtemp(prefix="fluxdrive-bench-services-"))
    try:
        for key, env in SETTINGS.items():
            res[key] = _one_setting(sp, sc, env, dom, args, tmp / key)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    for key in SETTINGS:
        for ph in PHASES:
            r = res[key][ph]
            _say(
                f"{key:9s} {ph:5s} (runnable {r['runnable_mean']:.1f}): "
                + "; ".join(
                    f"{c} p50 {r[c]['p50_ms']:.1f} / p99 {r[c]['p99_ms']:.1f} / max "
                    f"{r[c]['max_ms']:.1f} ms ({r[c]['unanswered']} unanswered)"
                    for c in CALLS
                )
            )
    res["unanswered_total"] = sum(
        res[key][ph][c]["unanswered"] for key in SETTINGS for ph in PHASES for c in CALLS
    )
    if args.write:
        write_benchmark("services", res)
    return res


def _one_setting(sp: Path, sc, env: str, dom: int, args, tmp: Path) -> dict:
    """One graph with FLUXDRIVE_SERVICE_THREAD=env: its quiet phase, then its busy one."""
    from fluxdrive_bringup.inspect.commands import OPERATOR_NODE, Session
    from fluxdrive_bringup.launch.launcher import Launcher
    from fluxdrive_bringup.launch.runs import graph_for_scenario

    g = graph_for_scenario(sp, sc, None, "composed", duration_s=3600.0, domain_id=dom)
    g.env["FLUXDRIVE_SERVICE_THREAD"] = env
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp / "logs")
    out: dict = {}
    busy: list[subprocess.Popen] = []
    s = None
    try:
        launcher.start()
        _wait_frames(launcher, 2000)  # the run phase: kernels loaded, loop closed
        s = Session(domain_id=dom, wait_s=30.0, node_name=OPERATOR_NODE)
        _warm(s)
        for ph in PHASES:
            if ph == "busy":
                busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.busy)]
                _wait_running(busy)
            _say(f"FLUXDRIVE_SERVICE_THREAD={env}: {ph} phase, {args.calls} calls of each kind")
            out[ph] = _phase(s, args.calls)
        out["frames"] = launcher.progress[0] if launcher.progress else 0
    finally:
        for b in busy:
            b.kill()
            b.wait()
        if s is not None:
            s.close()
        launcher.stop()
    return out


def _wait_frames(launcher, k: int, timeout_s: float = 600.0) -> None:
    t_end = time.monotonic() + timeout_s
    while (launcher.progress is None or launcher.progress[0] < k) and time.monotonic() < t_end:
        time.sleep(0.1)
    if launcher.progress is None or launcher.progress[0] < k:
        raise SystemExit(f"benchmark services: the graph did not reach frame {k} in {timeout_s} s")


def _wait_running(procs: list[subprocess.Popen], cpu_s: float = 0.3) -> None:
    """Until each busy process has used `cpu_s` of CPU time (it runs, it is not starting)."""
    import psutil

    def used(p: subprocess.Popen) -> float:
        try:
            return sum(psutil.Process(p.pid).cpu_times()[:2])
        except psutil.Error:
            return 0.0

    t_end = time.monotonic() + 60.0
    while any(used(p) < cpu_s for p in procs) and time.monotonic() < t_end:
        time.sleep(0.05)


def _warm(s) -> None:
    """Every service found and answering once (discovery; the reset's caller check)."""
    from fluxdrive_bringup.inspect.commands import reset_fault

    for kind in CALLS:
        _call(s, kind, 0)
    reset_fault(s, "/controller/reset_fault")


def _call(s, kind: str, i: int):
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.parameter import Parameter

    from flux_drive_msgs.srv import ResetFault
    from fluxdrive_bringup.inspect.commands import _call as call

    if kind == "get":
        return call(s, GetParameters, "/controller/get_parameters",
                    GetParameters.Request(names=[PARAM]), CALL_TIMEOUT_S)  # fmt: skip
    if kind == "set":
        msg = Parameter(PARAM, value=PARAM_VALUES[i % 2]).to_parameter_msg()
        req = SetParameters.Request(parameters=[msg])
        return call(s, SetParameters, "/controller/set_parameters", req, CALL_TIMEOUT_S)
    return call(s, ResetFault, "/controller/reset_fault", ResetFault.Request(), CALL_TIMEOUT_S)


def _phase(s, n: int) -> dict:
    times: dict[str, list[float]] = {c: [] for c in CALLS}
    unanswered = dict.fromkeys(CALLS, 0)
    runnable: list[int] = []
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.1):
            with open("/proc/loadavg") as fh:
                runnable.append(int(fh.read().split()[3].split("/")[0]))

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    try:
        for i in range(n):
            for kind in CALLS:
                t0 = time.monotonic()
                try:
                    _call(s, kind, i)
                except TimeoutError:
                    unanswered[kind] += 1
                    continue
                times[kind].append(time.monotonic() - t0)
    finally:
        stop.set()
        th.join()
    out: dict = {"runnable_mean": round(statistics.fmean(runnable), 2) if runnable else None}
    for kind in CALLS:
        out[kind] = {**_stats(times[kind]), "unanswered": unanswered[kind]}
    return out


def _stats(ts: list[float]) -> dict:
    if not ts:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None, "n": 0}
    ms = sorted(1e3 * t for t in ts)

    def q(p: float) -> float:
        return round(ms[min(len(ms) - 1, round(p * (len(ms) - 1)))], 2)

    return {"p50_ms": q(0.5), "p99_ms": q(0.99), "max_ms": round(ms[-1], 2), "n": len(ms)}
