"""`./fluxdrive benchmark graph`: real-time factor of the lockstep graph against the
in-process runner, on the demo scenario (2 % speed / 150 % load: plant, six observers,
controller, recorder; every message recorded).

  lockstep_rtf    simulated time / wall time of the graph's lockstep loop (first frame to
                  last frame, as the plant measures it), 10 kHz PWM, composed layout;
                  the recorded bag is checked to hold every sample; the best of --repeat
                  runs, each run's in lockstep_rtf_runs and their median in
                  lockstep_rtf_median; host_steal_pct_runs: the share of CPU time the
                  virtual machine's host took away during each of those runs (/proc/stat)
  in_process_rtf  the same scenario and observers through fluxdrive.drive.sim.run_scenario
  graph_process_cpu_us_per_period, bag_writer_cpu_us_per_period
                  CPU per PWM period of the graph's process and of its helper (the
                  recorder's bag writer), over the middle 80 % of the run, least of the runs:
                  unlike the real-time factor these hardly move with other load
  cpu_bound_rtf   the real-time factor that CPU allows with a core for each (a quiet 2-core
                  machine): Ts / the larger of the two
  closed_loop_cpu_us_per_period  (--closed-loop) the graph's process with the driving
                  observer only and no recorder: what the per-period loop itself costs

  lockstep_rtf_scope   (--scope) the same run with the live scope attached: the scope tap
                  in the graph's process, the scope's web server, and a page reading every
                  envelope -- a WebSocket client, or with --scope-browser the real page in
                  headless chromium (its redraw rate is reported as scope_page_fps);
                  scope_cost_pct = 100 (1 - lockstep_rtf_scope / lockstep_rtf);
                  graph_cpu_s_per_sim_s(_scope): CPU seconds of the graph's process (with
                  its bag writer) per simulated second, without and with the scope, and
                  scope_cpu_cost_pct from them -- a figure that, unlike the real-time
                  factor, hardly moves with other load on the machine;
                  scope_server_cpu_s_per_sim_s: the scope server's own CPU

Options: --duration S (simulated seconds, default 3), --layouts composed,split,separate
(extra keys lockstep_rtf_<layout>), --repeat N (best of N; with --scope the runs with and
without alternate, so both see the same machine load), --closed-loop, --write (store the
result in results/benchmarks/graph.json, quoted by docs/performance.md).
Progress goes to stderr; the last line on stdout is a JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fluxdrive.cli.bench import benchmark_path, stamped, write_benchmark
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.io.graphfile import GraphSettings


def _say(text: str) -> None:
    print(f"[bench graph] {text}", file=sys.stderr, flush=True)


def bench_graph(argv: list[str]) -> dict:
    from fluxdrive_bringup.launch.runs import LAYOUTS

    args = _graph_parser().parse_args(argv)
    if args.scope_browser:
        args.scope = True
    sp = scenario_path(args.scenario)
    layouts = [x.strip() for x in args.layouts.split(",") if x.strip()]
    for lay in layouts:
        if lay not in LAYOUTS:
            raise SystemExit(f"unknown layout {lay!r}; choose from {LAYOUTS}")
    sc, in_rtf = _in_process_rtf(sp, args.duration)
    first_cpu: list[dict] = []  # CPU figures of the runs of the first layout, without scope
    out: dict = {}
    page: dict = {}
    runs: dict[str, list[float]] = {}  # every run's real-time factor, by layout
    steal: dict[str, list[float | None]] = {}  # and the host's steal time over it
    tmp = Path(tempfile.mkdtemp(prefix="fluxdrive-bench-"))
    try:
        for lay in layouts:
            best: dict[bool, float] = {}
            cpus: dict[bool, list[dict]] = {}
            for rep in range(args.repeat):
                for with_scope in [False, True] if args.scope else [False]:
                    before = host_cpu_times()
                    rtf, c, seen = _graph_run(args, sp, sc, lay, rep, with_scope, tmp)
                    if not with_scope:
                        runs.setdefault(lay, []).append(round(rtf, 3))
                        steal.setdefault(lay, []).append(steal_pct(before, host_cpu_times()))
                    page = seen or page
                    if c:
                        cpus.setdefault(with_scope, []).append(c)
                        if lay == layouts[0] and not with_scope:
                            first_cpu.append(c)
                    best[with_scope] = max(best.get(with_scope, 0.0), rtf)
            out.update(_layout_figures(lay, best, cpus, args.scope))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res = _graph_result(args, sc, layouts, out, page, in_rtf)
    # the spread behind the best: a 2-core machine's scheduling moves a run by +-20 %
    res["lockstep_rtf_runs"] = runs[layouts[0]]
    res["lockstep_rtf_median"] = round(statistics.median(runs[layouts[0]]), 3)
    # a virtual machine's CPUs are shared with other guests: the share of time they were
    # taken away during each run says how quiet the host was
    res["host_steal_pct_runs"] = steal[layouts[0]]
    res.update(cpu_figures(first_cpu, sc.machine.ts_s))
    if args.closed_loop:
        res.update(closed_loop_cpu(sp, args.duration, args.domain_id, sc.machine.ts_s))
    if args.write:
        write_benchmark("graph", res)
    return res


def _graph_parser() -> argparse.ArgumentParser:
    from fluxdrive_bringup.launch.runs import DEMO_SCENARIO, LAYOUTS

    ap = Parser(prog="fluxdrive benchmark graph", description=__doc__)
    ap.add_argument("--duration", type=float, default=3.0, help="simulated seconds (default 3)")
    ap.add_argument("--scenario", default=DEMO_SCENARIO)
    ap.add_argument(
        "--layouts",
        default="composed",
        help=f"comma-separated, of {','.join(LAYOUTS)} (first = lockstep_rtf)",
    )
    ap.add_argument("--repeat", type=int, default=1, help="best of N graph runs per layout")
    option(ap, "--domain-id", GraphSettings)
    ap.add_argument(
        "--scope",
        action="store_true",
        help="also measure with the live scope attached (lockstep_rtf_scope)",
    )
    ap.add_argument(
        "--scope-browser",
        action="store_true",
        help="with --scope: the page in headless chromium instead of a plain WebSocket client",
    )
    ap.add_argument(
        "--closed-loop",
        action="store_true",
        help="also measure the closed loop alone (plant, driving observer, controller)",
    )
    ap.add_argument("--write", action="store_true", help="write results/benchmarks/graph.json")
    return ap


def _in_process_rtf(sp: Path, duration_s: float):
    """The in-process runner's real-time factor on the scenario (kernels warmed up first);
    (the shortened scenario, its real-time factor)."""
    from fluxdrive.drive.sim import run_scenario

    from fluxdrive_bringup.launch.runs import shorten

    sc = load_scenario(sp)
    shorten(sc, min(0.05, duration_s))
    _say("in-process: compiling / warming up ...")
    run_scenario(sc, progress=False)
    sc = load_scenario(sp)
    shorten(sc, duration_s)
    t0 = time.perf_counter()
    run_scenario(sc, progress=False)
    wall_ip = time.perf_counter() - t0
    in_rtf = sc.duration_s / wall_ip
    _say(
        f"in-process: {sc.n_periods} periods, {len(sc.observers)} observers in "
        f"{wall_ip:.2f} s = real-time factor {in_rtf:.2f}"
    )
    return sc, in_rtf


def _graph_run(args, sp: Path, sc, lay: str, rep: int, with_scope: bool, tmp: Path):
    """One graph run: (its lockstep real-time factor, CPU per simulated second, the scope
    page's figures); raises when it failed or lost samples."""
    from fluxdrive_bringup.launch.runs import result_from_bag, run_graph

    tag = f"{lay}-{rep}" + ("-scope" if with_scope else "")
    bag = tmp / f"bag-{tag}"
    what = (
        (" with the scope" + (" (chromium)" if args.scope_browser else " (WebSocket client)"))
        if with_scope
        else ""
    )
    _say(f"graph ({lay}){what}, run {rep + 1}/{args.repeat}: {args.duration:g} s simulated ...")
    watcher = ScopeWatcher(args.scope_browser) if with_scope else None
    cpu = CpuWatcher()

    def watch(launcher, watcher=watcher, cpu=cpu) -> None:
        import threading

        threading.Thread(target=cpu.run, args=(launcher,), daemon=True).start()
        if watcher is not None:
            watcher.run(launcher)

    r = run_graph(
        sp,
        out=tmp / f"run-{tag}",
        bag=bag,
        layout=lay,
        duration_s=args.duration,
        domain_id=args.domain_id,
        quiet=True,
        timeout=600.0,
        progress=False,
        scope=with_scope,
        scope_port=0,
        watch=watch,
    )
    cpu.stop()
    if r["code"] != 0 or r["lockstep_rtf"] is None:
        raise RuntimeError(
            f"graph run ({lay}) failed (exit {r['code']}); logs in {tmp / f'run-{tag}' / 'logs'}"
        )
    _, arr = result_from_bag(bag, load_scenario(sp), args.duration)
    missing = sum(arr["missing"].values())
    page: dict = {}
    extra = ""
    if watcher is not None:
        watcher.stop()
        page = watcher.summary(r["loop_wall_s"] or 1.0)
        extra = _page_note(page)
        if page["scope_envelopes"] == 0:
            raise RuntimeError(
                f"the scope delivered nothing ({lay}); logs in {tmp / f'run-{tag}' / 'logs'}"
            )
    c = cpu.per_sim_s(sc.machine.ts_s)
    if c:
        extra += f"; CPU per simulated second: graph process {c['graph']:.2f} s" + (
            f", scope server {c['scope']:.2f} s" if "scope" in c else ""
        )
    _say(
        f"graph ({lay}){what}: {r['frames']} frames in "
        f"{r['loop_wall_s']:.2f} s = real-time factor "
        f"{r['lockstep_rtf']:.3f}; bag: {arr['n']} frames, {missing} samples "
        f"missing{extra}"
    )
    if missing:
        raise RuntimeError(f"graph run ({lay}) lost {missing} samples: {arr['missing']}")
    shutil.rmtree(bag, ignore_errors=True)
    return r["lockstep_rtf"], c, page


def _page_note(page: dict) -> str:
    return (
        f"; scope: {page['scope_envelopes']} envelopes to the page "
        f"({page['scope_envelopes_per_s']:.1f}/s)"
        + (f", page redraws {page['scope_page_fps']:.0f}/s" if "scope_page_fps" in page else "")
    )


def _layout_figures(
    lay: str, best: dict[bool, float], cpus: dict[bool, list[dict]], scope: bool
) -> dict:
    """A layout's best real-time factors and, with the scope, what the scope costs."""
    out = {f"lockstep_rtf_{lay}": round(best[False], 3)}
    if not scope:
        return out
    out[f"lockstep_rtf_scope_{lay}"] = round(best[True], 3)
    if cpus.get(False) and cpus.get(True):
        # least CPU per simulated second of each: the run least disturbed by
        # other load on the machine
        g0 = min(c["graph"] for c in cpus[False])
        g1 = min(c["graph"] for c in cpus[True])
        out[f"graph_cpu_s_per_sim_s_{lay}"] = round(g0, 3)
        out[f"graph_cpu_s_per_sim_s_scope_{lay}"] = round(g1, 3)
        out[f"scope_cpu_cost_pct_{lay}"] = round(100.0 * (g1 / g0 - 1.0), 1)
        sv = [c["scope"] for c in cpus[True] if "scope" in c]
        if sv:
            out[f"scope_server_cpu_s_per_sim_s_{lay}"] = round(min(sv), 3)
    return out


def _graph_result(args, sc, layouts: list[str], out: dict, page: dict, in_rtf: float) -> dict:
    res = {
        "lockstep_rtf": out[f"lockstep_rtf_{layouts[0]}"],
        "in_process_rtf": round(in_rtf, 2),
        "layout": layouts[0],
        "pwm_hz": sc.machine.pwm_hz,
        "observers": len(sc.observers),
        "simulated_s": args.duration,
        "recorded": True,
    }
    if args.scope:
        rs = out[f"lockstep_rtf_scope_{layouts[0]}"]
        res.update(
            lockstep_rtf_scope=rs,
            scope_cost_pct=round(100.0 * (1.0 - rs / res["lockstep_rtf"]), 1),
            scope_client="chromium" if args.scope_browser else "websocket",
            **page,
        )
        for k in (
            "graph_cpu_s_per_sim_s",
            "graph_cpu_s_per_sim_s_scope",
            "scope_cpu_cost_pct",
            "scope_server_cpu_s_per_sim_s",
        ):
            if f"{k}_{layouts[0]}" in out:
                res[k] = out[f"{k}_{layouts[0]}"]
    if len(layouts) > 1:
        res.update(out)
    return res


def host_cpu_times() -> tuple[int, int] | None:
    """(steal, total) jiffies of all CPUs since boot (/proc/stat; None where there is none):
    steal is time a virtual machine's CPU was ready but the host ran something else."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu" or len(fields) < 9:
        return None
    ticks = [int(x) for x in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return ticks[7], sum(ticks)


def steal_pct(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """The host's steal time between two host_cpu_times readings, in % of all CPU time."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return round(100.0 * (after[0] - before[0]) / (after[1] - before[1]), 1)


def cpu_figures(runs: list[dict], ts_s: float) -> dict:
    """CPU per PWM period of the graph's process and of its helpers (the bag writer), the
    least of the runs (the one least disturbed by other load), and the real-time factor that
    CPU allows when each has a core of its own (a quiet 2-core machine): the arithmetic
    behind the measured real-time factor, which moves with the machine's load."""
    runs = [c for c in runs if "graph_process" in c]
    if not runs:
        return {}
    per = 1e6 * ts_s  # us of CPU per period = s of CPU per simulated s x 1e6 x ts
    graph_us = min(c["graph_process"] for c in runs) * per
    helpers_us = min(c["helpers"] for c in runs) * per
    slowest = max(graph_us, helpers_us)
    return {
        "graph_process_cpu_us_per_period": round(graph_us, 1),
        "bag_writer_cpu_us_per_period": round(helpers_us, 1),
        "cpu_bound_rtf": round(1e6 * ts_s / slowest, 3) if slowest > 0 else None,
    }


def closed_loop_cpu(sp: Path, duration_s: float, domain_id: int | None, ts_s: float) -> dict:
    """CPU per PWM period of the closed loop alone: the scenario with its driving observer
    only and no recorder (the plant's truth and the controller's state, read by nobody in
    the process, then go out over DDS, which this figure includes)."""
    from fluxdrive.drive.scenario import save_scenario

    from fluxdrive_bringup.launch.runs import run_graph

    sc = load_scenario(sp)
    sc.observers = {sc.driving: sc.observers[sc.driving]}
    tmp = Path(tempfile.mkdtemp(prefix="fluxdrive-bench-loop-"))
    try:
        loop_sp = save_scenario(sc, tmp / sp.name)
        cpu = CpuWatcher()

        def watch(launcher) -> None:
            cpu.run(launcher)

        _say(f"closed loop alone (plant, {sc.driving}, controller): {duration_s:g} s ...")
        r = run_graph(
            loop_sp,
            out=tmp / "run",
            bag=None,
            duration_s=duration_s,
            domain_id=domain_id,
            quiet=True,
            timeout=600.0,
            progress=False,
            watch=watch,
        )
        cpu.stop()
        c = cpu.per_sim_s(ts_s)
        if r["code"] != 0 or "graph_process" not in c:
            raise RuntimeError(f"closed-loop run failed (exit {r['code']}); logs in {tmp}")
        us = c["graph_process"] * 1e6 * ts_s
        _say(f"closed loop alone: {us:.1f} us of CPU per period, RTF {r['lockstep_rtf']:.3f}")
        return {"closed_loop_cpu_us_per_period": round(us, 1)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class CpuWatcher:
    """CPU time of the graph's process (the plant's, with its helper processes) and of the
    scope server against the plant's progress: CPU seconds per simulated second over the
    middle of the run (start-up and finalising left out).  Unlike the real-time factor it
    hardly depends on what else the machine is doing."""

    def __init__(self):
        import threading

        self.done = threading.Event()
        # (k, graph cpu with its helpers, scope cpu, graph process alone)
        self.samples: list[tuple[int, float, float, float]] = []

    @staticmethod
    def _own_cpu(p) -> float:
        try:
            t = p.cpu_times()
            return t.user + t.system
        except Exception:  # noqa: BLE001 - the process ended
            return float("nan")

    @staticmethod
    def _cpu(p) -> float:
        try:
            t = p.cpu_times()
            tot = t.user + t.system
            for ch in p.children(recursive=True):
                try:
                    c = ch.cpu_times()
                    tot += c.user + c.system
                except Exception:  # noqa: BLE001 - gone meanwhile
                    pass
            return tot
        except Exception:  # noqa: BLE001 - the process ended
            return float("nan")

    def run(self, launcher) -> None:
        import psutil

        graph = scope = None
        while not self.done.is_set():
            time.sleep(0.2)
            if graph is None:
                for p in launcher.procs:
                    if p.popen is None:
                        continue
                    if any(n.node == "plant" for n in p.nodes):
                        graph = psutil.Process(p.popen.pid)
                    elif any(n.name == "scope" for n in p.nodes):
                        scope = psutil.Process(p.popen.pid)
                if graph is None:
                    continue
            prog = launcher.progress
            if prog is None:
                continue
            self.samples.append(
                (
                    prog[0],
                    self._cpu(graph),
                    self._cpu(scope) if scope is not None else float("nan"),
                    self._own_cpu(graph),
                )
            )
            if prog[0] >= prog[1]:
                break

    def stop(self) -> None:
        self.done.set()

    def per_sim_s(self, ts_s: float) -> dict[str, float]:
        import math

        if not self.samples:
            return {}
        n = self.samples[-1][0]
        mid = [s for s in self.samples if 0.1 * n <= s[0] <= 0.9 * n and math.isfinite(s[1])]
        if len(mid) < 2 or mid[-1][0] <= mid[0][0]:
            return {}
        dk = (mid[-1][0] - mid[0][0]) * ts_s
        out = {"graph": (mid[-1][1] - mid[0][1]) / dk}
        if math.isfinite(mid[0][3]) and math.isfinite(mid[-1][3]):
            # the graph's process alone, and its helpers (the recorder's bag writer)
            out["graph_process"] = (mid[-1][3] - mid[0][3]) / dk
            out["helpers"] = out["graph"] - out["graph_process"]
        if math.isfinite(mid[0][2]) and math.isfinite(mid[-1][2]):
            out["scope"] = (mid[-1][2] - mid[0][2]) / dk
        return out


class ScopeWatcher:
    """What watches the scope during a benchmark run: a WebSocket client that reads every
    envelope, or the real page in headless chromium (playwright)."""

    def __init__(self, browser: bool):
        import threading

        self.browser = browser
        self.done = threading.Event()
        self.n = 0
        self.bytes = 0
        self.fps: list[float] = []
        self.draw_ms: list[float] = []

    def run(self, launcher) -> None:
        t_end = time.monotonic() + 120.0
        while not launcher.scope_urls and time.monotonic() < t_end and not self.done.is_set():
            time.sleep(0.05)
        if not launcher.scope_urls:
            return
        url = launcher.scope_urls[0]
        try:
            if self.browser:
                self._page(url)
            else:
                self._ws(url)
        except Exception as exc:  # noqa: BLE001 - the graph ended under us: report what we got
            if not self.done.is_set():
                _say(f"scope client: {type(exc).__name__}: {exc}")

    def _ws(self, url: str) -> None:
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        ws_url = url.replace("http://", "ws://").replace("/?token=", "/ws?token=")
        with connect(ws_url, max_size=None) as ws:
            while not self.done.is_set():
                try:
                    m = ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                except ConnectionClosed:  # the scope ends with the run
                    return
                if isinstance(m, str) and m.startswith('{"hello"'):
                    continue
                self.n += 1
                self.bytes += len(m)

    def _page(self, url: str) -> None:
        import shutil as sh

        from playwright.sync_api import sync_playwright

        exe = sh.which("chromium") or "/usr/bin/chromium"
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path=exe, args=["--no-sandbox"])
            page = b.new_page(viewport={"width": 1600, "height": 1100})
            page.goto(url)
            while not self.done.is_set():
                page.wait_for_timeout(1000)
                s = page.evaluate("({...window.scopeStats})")
                self.n = s["envelopes"]
                if s["lastSeq"] > 0:
                    self.fps.append(float(s["fps"]))
                    self.draw_ms.append(float(s.get("drawMs") or 0.0))
            b.close()

    def stop(self) -> None:
        self.done.set()
        time.sleep(0.2)

    def summary(self, wall_s: float) -> dict:
        out = {
            "scope_envelopes": self.n,
            "scope_envelopes_per_s": round(self.n / max(wall_s, 1e-9), 1),
        }
        if self.bytes:
            out["scope_kb_per_s"] = round(self.bytes / 1e3 / max(wall_s, 1e-9), 1)
        if self.fps:
            fps = sorted(self.fps[1:] or self.fps)  # the first second loads the page
            out["scope_page_fps"] = round(fps[len(fps) // 2], 1)  # median
            dm = sorted(self.draw_ms[1:] or self.draw_ms)
            out["scope_page_draw_ms"] = round(dm[len(dm) // 2], 1)  # one frame, all charts
        return out


def main(argv: list[str] | None = None) -> int:
    res = bench_graph(sys.argv[1:] if argv is None else argv)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())


PACED_DOC = """`./fluxdrive benchmark paced`: timing of the paced loop (the plant held to the wall
clock at rate_factor x real time, 10 kHz PWM at rate 1), with the demo scenario's four
observers, the controller and the recorder; composed layout by default.

  lateness_p50/p99/max_periods  how late each frame went out against its due wall time,
                  in PWM periods (the plant's pacing record: one entry per frame)
  duty_lateness_p50/p99/max_periods  how late each duty command came against its deadline
                  (two periods after the frame it answers went out, or the due time of the
                  frame it drives if later; negative: early), in PWM periods
  late_frames_per_min   frames more than one period late, per minute of wall time
  late_duties_per_min   duty commands that came after their deadline (the plant waited
                  with the previous duty in effect; time slipped by the wait)
  slips_per_min   the plant itself was more than 50 periods late and let time slip
  watchdog_trips  PWM switched off because no duty command at all came for watchdog_s
  latched_faults  faults the controller latched (watchdog or any protection trip)
  rtf             simulated time / wall time actually achieved

Options: --duration S (simulated seconds, default 2), --minutes M (instead: paced running
for M minutes of wall time, the graph held as `tune` holds it -- use a scenario whose hold
point does not trip I2t, e.g. tune_60rpm_80load), --rate R (default 1.0), --watchdog-s S
(the plant's silence limit, default 1), --layout composed|split|separate,
--background-load (one busy core: a child process spinning for the whole run, the
realistic load of a shared bench PC; its figures are loaded figures), --write LABEL (also
store the result under LABEL in results/benchmarks/paced.json).  Progress on stderr; the
last line is JSON."""


def bench_paced(argv: list[str]) -> dict:
    args = _paced_parser().parse_args(argv)
    sp = scenario_path(args.scenario)
    r, p, text = _paced_run(args, sp)
    res = _paced_result(args, sp, r, p, text)
    _say(
        f"{res['frames']} frames: lateness p50 {res['lateness_p50_periods']} / p99 "
        f"{res['lateness_p99_periods']} / max {res['lateness_max_periods']} periods; "
        f"{res['late_frames_per_min']} late frames/min, {res['late_duties_per_min']} late "
        f"duties/min, "
        f"{res['slips_per_min']} slips/min, {res['watchdog_trips']} watchdog trips; "
        f"achieved real-time factor {res['rtf']}"
    )
    if args.write:
        _write_paced(args.write, res)
    return res


def _paced_parser() -> argparse.ArgumentParser:
    from fluxdrive_ros.runner import load_class

    from fluxdrive_bringup.launch.runs import DEMO_SCENARIO, LAYOUTS

    ap = Parser(prog="fluxdrive benchmark paced", description=PACED_DOC)
    ap.add_argument("--duration", type=float, default=2.0, help="simulated seconds")
    ap.add_argument("--minutes", type=float, default=0.0, help="wall minutes (0: --duration)")
    # the plant's own fields (rate_factor, watchdog_s): what it would accept, said at once
    timing = load_class("plant").TIMING_SETTINGS
    option(ap, "--watchdog-s", timing, help="plant's silence limit (wall time)")
    ap.add_argument("--write", metavar="LABEL", help="store under LABEL in paced.json")
    option(ap, "--rate", timing, "rate_factor", help="rate_factor (1: real time)")
    ap.add_argument("--layout", choices=LAYOUTS, default="composed")
    ap.add_argument("--scenario", default=DEMO_SCENARIO)
    option(ap, "--domain-id", GraphSettings)
    ap.add_argument(
        "--background-load",
        action="store_true",
        help="one busy core: a spinning child process for the whole run",
    )
    return ap


def _paced_run(args, sp: Path):
    """The paced graph run: (run_graph's summary, the plant's pacing record, the logs'
    text); raises when it failed."""
    import re

    from fluxdrive_bringup.launch.runs import run_graph

    plant: dict[str, object] = {
        "mode": "paced",
        "rate_factor": args.rate,
        "watchdog_s": args.watchdog_s,
    }
    extra: dict[str, dict[str, object]] = {"plant": plant}
    duration: float = args.duration
    watch = None
    if args.minutes > 0:  # held until stopped, as `tune` holds it
        duration = 0.0
        for n in [*load_scenario(sp).observers, "controller"]:
            extra[n] = {"exit_on_done": False}

        def watch(launcher) -> None:
            while not (launcher.progress and launcher.progress[0] > 2):  # the loop runs
                time.sleep(0.2)
            time.sleep(60.0 * args.minutes)
            launcher.stop()

    tmp = Path(tempfile.mkdtemp(prefix="fluxdrive-bench-paced-"))
    spinner = (
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        if args.background_load
        else None
    )
    try:
        _say(
            f"paced graph ({args.layout}) at rate {args.rate:g}"
            + (", one busy core in the background" if args.background_load else "")
            + (
                f": {args.minutes:g} min of wall time ..."
                if args.minutes > 0
                else f": {args.duration:g} s simulated ..."
            )
        )
        r = run_graph(
            sp,
            out=tmp / "run",
            bag=tmp / "bag",
            layout=args.layout,
            duration_s=duration,
            domain_id=args.domain_id,
            quiet=True,
            timeout=600.0 + 60.0 * args.minutes,
            progress=False,
            extra=extra,
            watch=watch,
        )
        text = "\n".join(
            p.read_text(errors="replace") for p in sorted((tmp / "run" / "logs").glob("*.log"))
        )
        m = re.search(r"pacing (\{.*\})", text)
        if r["code"] != 0 or m is None:
            raise RuntimeError(
                f"paced graph failed (exit {r['code']}); logs in {tmp / 'run' / 'logs'}"
            )
        pacing = json.loads(m.group(1))
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    shutil.rmtree(tmp, ignore_errors=True)  # kept (logs) when the run failed
    return r, pacing, text


def _paced_result(args, sp: Path, r: dict, p: dict, text: str) -> dict:
    import re

    wall_min = p["wall_s"] / 60.0  # the paced run proper, from the first duty command
    return {
        "layout": args.layout,
        "scenario": Path(sp).stem,
        "rate_factor": args.rate,
        "frames_per_s_due": round(args.rate / r["scenario"].machine.ts_s),
        "wall_min": round(wall_min, 2),
        "watchdog_s": args.watchdog_s,
        "background_load": args.background_load,
        "observers": 4,
        "recorded": True,
        "frames": p["frames"],
        "period_us": round(p["period_s"] * 1e6, 1),
        "lateness_p50_periods": round(p["lateness_p50_periods"], 3),
        "lateness_p99_periods": round(p["lateness_p99_periods"], 3),
        "lateness_max_periods": round(p["lateness_max_periods"], 1),
        "duty_lateness_p50_periods": round(p.get("duty_lateness_p50_periods", 0.0), 3),
        "duty_lateness_p99_periods": round(p.get("duty_lateness_p99_periods", 0.0), 3),
        "duty_lateness_max_periods": round(p.get("duty_lateness_max_periods", 0.0), 1),
        "late_frames_per_min": round(p["late_frames"] / wall_min, 1),
        "late_duties_per_min": round(p["late_duties"] / wall_min, 1),
        "slips_per_min": round(p["slips"] / wall_min, 1),
        "watchdog_trips": p["watchdog_trips"],
        "latched_faults": len(re.findall(r"PWM off \(latched\)", text)),
        "rtf": round(p["frames"] * r["scenario"].machine.ts_s / p["wall_s"], 3),
    }


def _write_paced(label: str, res: dict) -> None:
    """Merge one run into results/benchmarks/paced.json under `label` (the file the docs
    quote), with when and how loaded the machine was."""
    path = benchmark_path("paced")
    doc = json.loads(path.read_text()) if path.exists() else {}
    doc[label] = stamped(res)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    _say(f"written {path} [{label}]")
