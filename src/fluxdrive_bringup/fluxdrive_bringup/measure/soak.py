"""`./fluxdrive soak`: the load checks of a long bench session.

1. Lockstep soak: the composed lockstep graph of a scenario (plant, observers, controller,
   recorder) runs for about --wall-s of wall time (default 300 s).  The simulated duration
   is set from a short calibration run's real-time factor, so the run ends by itself and
   every topic has a known message count: one frame, one estimate per observer, one
   controller state and one truth sample per PWM period.  The resident memory (VmRSS) of
   every process of the graph (bag-writer helper included) is sampled every --sample-s.
   Each process is judged after its own warm-up (20 % of the run, counted from the
   process's first sample, so a helper started late has its start-up excluded): its
   growth is the median of the last third of its samples minus the median of the first
   third; the sum over the processes must stay under --max-growth-mb.  The
   bag's per-topic counts are read from the mcap summary (independent of the recorder's
   own metadata.yaml, which is checked too) and must equal the number of periods.
2. Burst replay: the bag is published by `./fluxdrive replay --live` with no pacing
   (--rate 1e9) for --burst-loops passes into a KEEP_ALL reliable subscriber in this
   process; received must equal sent, and neither process may grow in memory from the
   first pass to the last.

Progress goes to stderr; the last stdout line is a JSON object with "ok" and the figures.
Exit code 0 when every check passed.  --write stores the figures in
results/benchmarks/soak.json, which docs/performance.md quotes.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from fluxdrive.core.schema import Parser
from fluxdrive.drive.scenario import REPO_ROOT, load_scenario, scenario_path
from fluxdrive.io.bagio import bag_counts
from fluxdrive_ros.topics import CONTROLLER_STATE, FRAME, TRUTH, estimate_topic

from fluxdrive_bringup.launch.domains import pick_domain_id
from fluxdrive_bringup.launch.launcher import Launcher
from fluxdrive_bringup.launch.runs import graph_for_scenario, shorten

SOAK_SCENARIO = "paper_4pct_fullload"


def _say(text: str) -> None:
    print(f"[soak] {text}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------ memory of processes
def _rss_kib(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def _pids_in_groups(pgids: set[int]) -> list[int]:
    """Every live process whose process group is one of `pgids` (a launched process and
    the helpers it started, such as the recorder's bag writer)."""
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        # pgrp is the 5th field; the command name (2nd) may contain spaces: split after ')'
        fields = stat.rsplit(")", 1)[-1].split()
        if len(fields) > 2 and int(fields[2]) in pgids:
            out.append(int(d))
    return out


def _label(pid: int) -> str:
    """Short name of a process: the container's process name, else the command."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().split(b"\0")
    except OSError:
        return str(pid)
    text = " ".join(a.decode(errors="replace") for a in argv if a)
    if '"process": "' in text:
        return text.split('"process": "', 1)[1].split('"', 1)[0]
    for mod in ("bagwriter", "replay"):
        if mod in text:
            return mod
    return Path(argv[0].decode(errors="replace")).name or str(pid)


def _median_growth(steady: list[float]) -> tuple[float, float, float]:
    """(MiB, MiB, growth): medians of the first and the last third of `steady`, and their
    difference.  Medians, because the bag writer's buffers and the allocator make single
    samples swing by tens of MiB; a leak moves the medians, a swing does not."""
    k = max(1, len(steady) // 3)
    start = statistics.median(steady[:k])
    end = statistics.median(steady[-k:])
    return start, end, end - start


def growth_per_process(
    per_proc: dict[str, list[tuple[float, float]]], warmup_s: float
) -> dict[str, tuple[float, float, float]]:
    """Growth of each process from its own steady state: a process's baseline is taken
    from its samples once it has been running (been seen) for `warmup_s`, so a process
    that starts late (the bag writer starts after the kernels compiled) has its own
    start-up excluded, while a leak in it still moves its medians.  A process with fewer
    than three samples after its own warm-up cannot be judged: its triple is NaN."""
    out: dict[str, tuple[float, float, float]] = {}
    for lab, series in per_proc.items():
        if not series:
            continue
        cutoff = series[0][0] + warmup_s
        steady = [m for t, m in series if t >= cutoff]
        out[lab] = _median_growth(steady) if len(steady) >= 3 else (float("nan"),) * 3
    return out


def graph_growth(
    per_proc: dict[str, list[tuple[float, float]]], warmup_s: float
) -> tuple[float, float, float, dict[str, tuple[float, float, float]]]:
    """(MiB, MiB, growth, per process): the sums over the processes that can be judged of
    their own baselines, ends and growths (`growth_per_process`), and the per-process
    triples."""
    per = growth_per_process(per_proc, warmup_s)
    judged = [v for v in per.values() if v[2] == v[2]]
    if not judged:
        return float("nan"), float("nan"), float("nan"), per
    start, end, growth = (sum(v[i] for v in judged) for i in range(3))
    return start, end, growth, per


class RssSampler(threading.Thread):
    """Samples the VmRSS [MiB] of a set of process groups (or pids) periodically, summed
    and per process."""

    def __init__(self, period_s: float, groups=None, pids=None):
        super().__init__(daemon=True)
        self.period_s = period_s
        self.groups = groups  # callable -> set of pgids
        self.pids = pids  # callable -> list of pids
        self.samples: list[tuple[float, float]] = []  # (monotonic s, MiB summed)
        self.per_proc: dict[str, list[tuple[float, float]]] = {}  # label -> (s, MiB)
        self.stop_evt = threading.Event()

    def sample(self) -> float:
        pids = list(self.pids()) if self.pids else _pids_in_groups(self.groups())
        now = time.monotonic()
        total = 0.0
        for pid in pids:
            mib = _rss_kib(pid) / 1024.0
            total += mib
            if mib > 0:
                lab = f"{_label(pid)}[{pid}]"
                self.per_proc.setdefault(lab, []).append((now, round(mib, 1)))
        return total

    def run(self) -> None:
        while not self.stop_evt.is_set():
            mib = self.sample()
            if mib > 0:
                self.samples.append((time.monotonic(), mib))
            self.stop_evt.wait(self.period_s)

    def warmup_s(self, warmup_frac: float = 0.2) -> float:
        """The warm-up: `warmup_frac` of the sampled span [s]."""
        if len(self.samples) < 2:
            return 0.0
        return warmup_frac * (self.samples[-1][0] - self.samples[0][0])

    def growth_mb(self, warmup_frac: float = 0.2) -> tuple[float, float, float]:
        """(MiB, MiB, growth) of the summed samples after the warm-up (`_median_growth`)."""
        if len(self.samples) < 4:
            return (float("nan"),) * 3
        cutoff = self.samples[0][0] + self.warmup_s(warmup_frac)
        steady = [m for t, m in self.samples if t >= cutoff]
        if len(steady) < 3:
            steady = [m for _, m in self.samples[-3:]]
        return _median_growth(steady)


# ------------------------------------------------------------------ bag message counts
# ------------------------------------------------------------------ 1. lockstep soak
def _calibrate(sp: Path, tmp: Path, calib_s: float) -> float:
    """Steady lockstep real-time factor of the scenario's graph: a short run, the rate
    taken from the plant's progress reports after the first half (start-up, compilation
    and discovery excluded)."""
    sc = load_scenario(sp)
    shorten(sc, calib_s)
    g = graph_for_scenario(sp, sc, tmp / "calib-bag", "composed", calib_s, pick_domain_id())
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp / "calib-logs")
    ticks: list[tuple[int, float]] = []
    done = threading.Event()

    def poll() -> None:
        while not done.wait(0.1):
            pr = launcher.progress
            if pr and (not ticks or pr[0] != ticks[-1][0]):
                ticks.append((pr[0], pr[2]))

    threading.Thread(target=poll, daemon=True).start()
    code = launcher.run(timeout=300.0)
    done.set()
    shutil.rmtree(tmp / "calib-bag", ignore_errors=True)
    if code != 0:
        raise RuntimeError(f"calibration run failed (exit {code}); logs in {tmp / 'calib-logs'}")
    late = [t for t in ticks if t[0] >= 0.5 * sc.n_periods] or ticks[-2:]
    if len(late) < 2 or late[-1][1] <= late[0][1]:
        if launcher.progress is None:
            raise RuntimeError(
                f"calibration run reported no progress; logs in {tmp / 'calib-logs'}"
            )
        k, _, wall = launcher.progress
        return k * sc.machine.ts_s / wall
    return (late[-1][0] - late[0][0]) * sc.machine.ts_s / (late[-1][1] - late[0][1])


def lockstep_soak(
    sp: Path, wall_s: float, sample_s: float, max_growth_mb: float, tmp: Path, calib_s: float = 4.0
) -> dict:
    _say(f"calibration: {calib_s:g} s simulated through the graph ...")
    rtf = _calibrate(sp, tmp, calib_s)
    sim_s = max(1.0, round(wall_s * rtf, 1))
    _say(
        f"calibration: steady real-time factor {rtf:.3f}; soak: {sim_s:g} s simulated "
        f"(about {wall_s:g} s of wall time), RSS every {sample_s:g} s"
    )
    sc = load_scenario(sp)
    shorten(sc, sim_s)
    bag = tmp / "soak-bag"
    g = graph_for_scenario(sp, sc, bag, "composed", sim_s, pick_domain_id())
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp / "soak-logs")
    sampler = RssSampler(
        sample_s, groups=lambda: {p.popen.pid for p in launcher.procs if p.popen is not None}
    )
    last = [0.0]

    def progress() -> None:
        while not sampler.stop_evt.wait(10.0):
            pr = launcher.progress
            mib = sampler.samples[-1][1] if sampler.samples else float("nan")
            if pr and time.monotonic() - last[0] > 9.0:
                last[0] = time.monotonic()
                _say(
                    f"{pr[0] * sc.machine.ts_s:7.1f}/{sim_s:g} s simulated, "
                    f"{pr[2]:6.1f} s wall, graph RSS {mib:.1f} MiB"
                )

    t0 = time.monotonic()
    sampler.start()
    threading.Thread(target=progress, daemon=True).start()
    code = launcher.run(timeout=wall_s * 4 + 120)
    sampler.stop_evt.set()
    wall = time.monotonic() - t0
    if code != 0:
        raise RuntimeError(f"soak graph failed (exit {code}); logs in {tmp / 'soak-logs'}")
    n = sc.n_periods
    mc, meta = bag_counts(bag)
    expect = [FRAME, TRUTH, CONTROLLER_STATE, *[estimate_topic(o) for o in sc.observers]]
    lost = {t: n - mc.get(t, 0) for t in expect if mc.get(t, 0) != n}
    meta_diff = {
        t: (mc.get(t), meta.get(t)) for t in set(mc) | set(meta) if mc.get(t) != meta.get(t)
    }
    rss = _rss_figures(sampler)
    start, end, growth = rss["rss_mb_after_warmup"], rss["rss_mb_end"], rss["rss_growth_mb"]
    bag_mb = sum(f.stat().st_size for f in bag.iterdir()) / 2**20
    res = {
        "soak_wall_s": round(wall, 1),
        "soak_simulated_s": sim_s,
        "periods": n,
        "lockstep_rtf": round(n * sc.machine.ts_s / (launcher.progress[2] or wall), 3)
        if launcher.progress
        else None,
        "messages": int(sum(mc.values())),
        "lost": lost,
        "lost_messages": int(sum(lost.values())),
        "metadata_mismatch": meta_diff,
        "bag_mb": round(bag_mb, 1),
        **rss,
    }
    res["soak_ok"] = bool(not lost and not meta_diff and growth <= max_growth_mb)
    _say(
        f"soak: {n} periods in {wall:.1f} s, {res['messages']} messages, lost {lost or 0}, "
        f"RSS {start:.1f} -> {end:.1f} MiB (growth {growth:+.1f} MiB, limit "
        f"{max_growth_mb:g}), bag {bag_mb:.0f} MiB"
    )
    shutil.rmtree(bag, ignore_errors=True)
    return res


def _rss_figures(sampler: RssSampler) -> dict:
    """The graph's memory figures: per-process baselines and growths (each process after
    its own warm-up, `graph_growth`), their sums, and the series sampled."""
    start, end, growth, per = graph_growth(sampler.per_proc, sampler.warmup_s())
    _say(
        "RSS growth per process after its own warm-up: "
        + ", ".join(f"{lab} {g:+.1f} MiB" for lab, (_, _, g) in per.items())
    )
    return {
        "rss_mb_after_warmup": round(start, 1),
        "rss_mb_end": round(end, 1),
        "rss_growth_mb": round(growth, 1),
        "rss_growth_mb_per_process": {
            lab: None if g != g else round(g, 1) for lab, (_, _, g) in per.items()
        },
        "rss_samples": len(sampler.samples),
        "rss_mb_series": [round(m, 1) for _, m in sampler.samples],
        "rss_mb_per_process": {lab: [m for _, m in s] for lab, s in sampler.per_proc.items()},
    }


# ------------------------------------------------------------------ 2. burst replay
def burst_replay(bag: Path, loops: int, sample_s: float, max_growth_mb: float) -> dict:
    import rclpy
    from fluxdrive.io.bagio import topic_counts

    n_bag = topic_counts(bag).get(FRAME, 0)
    if n_bag == 0:
        raise RuntimeError(f"{bag}: no frames on {FRAME} to replay")
    total = n_bag * loops
    dom = pick_domain_id()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=dom)
    node, ex, state = _burst_sink(ctx, n_bag)
    _say(f"burst: {n_bag} frames x {loops} passes, unpaced, into a KEEP_ALL reliable reader")
    pub = _burst_publisher(bag, total, dom)
    sink_rss = RssSampler(sample_s, pids=lambda: [os.getpid()])
    pub_rss = RssSampler(sample_s, pids=lambda: [pub.pid] if pub.poll() is None else [])
    sink_rss.start()
    pub_rss.start()
    try:
        wall = _receive(ex, pub, state, total)
        err = pub.communicate(timeout=60)[1]
    finally:
        sink_rss.stop_evt.set()
        pub_rss.stop_evt.set()
        if pub.poll() is None:
            pub.kill()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    if pub.returncode != 0:
        tail = (err or "").strip().splitlines()[-1:]
        raise RuntimeError(f"burst publisher failed (exit {pub.returncode}): {tail}")
    # the first half fills the middleware's pools (the writer history of a KEEP_ALL burst)
    _, _, sg = sink_rss.growth_mb(0.5)
    _, _, pg = pub_rss.growth_mb(0.5)
    return _burst_result(total, state, wall, sg, pg, max_growth_mb)


def _burst_sink(ctx, n_bag: int):
    """A node counting the frames it receives and the ones out of order (within a pass the
    seqs are consecutive; each pass starts again): (node, executor, counts)."""
    import rclpy
    from fluxdrive.io.cdr import Decoder
    from rclpy.experimental import EventsExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from flux_drive_msgs.msg import PhaseFrame

    node = rclpy.create_node("soak_burst_sink", context=ctx)
    dec = Decoder("flux_drive_msgs/msg/PhaseFrame")
    state = {"got": 0, "prev": -1, "order_errors": 0}

    def on_frame(data: bytes) -> None:
        c = dec.codec_for(data)
        seq = int(c.unpack(data)[c.index("seq")])
        if state["got"] % n_bag != 0 and seq != state["prev"] + 1:
            state["order_errors"] += 1
        state["prev"] = seq
        state["got"] += 1

    # raw (no deserialisation) on the EventsExecutor, as the graph's own readers run
    node.create_subscription(
        PhaseFrame,
        FRAME,
        on_frame,
        QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE),
        raw=True,
    )
    ex = EventsExecutor(context=ctx)
    ex.add_node(node)
    return node, ex, state


def _burst_publisher(bag: Path, total: int, dom: int) -> subprocess.Popen:
    """`replay --live` of the bag, looped to `total` frames, as fast as it goes."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    cmd = [
        sys.executable,
        "-m",
        "fluxdrive.cli",
        "replay",
        str(bag),
        "--live",
        "--rate",
        "1e9",
        "--loop",
        "--max-frames",
        str(total),
        "--wait-s",
        "60",
    ]
    return subprocess.Popen(
        cmd,
        env=env,
        cwd=str(REPO_ROOT),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _receive(ex, pub: subprocess.Popen, state: dict, total: int) -> float:
    """Spin until every frame came (or the publisher ended and what was in flight did);
    the wall time from the first frame to the last [s]."""
    t0 = time.monotonic()
    t_first = None
    last_say = t0
    deadline = t0 + 600.0
    while time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        if t_first is None and state["got"]:
            t_first = now
        if state["got"] >= total:
            break
        if pub.poll() is not None and state["got"] < total:
            deadline = min(deadline, now + 10.0)  # what is in flight, then give up
        if now - last_say > 5.0:
            last_say = now
            _say(f"burst: {state['got']}/{total} frames received")
    return time.monotonic() - (t_first or t0)


def _burst_result(
    total: int, state: dict, wall: float, sg: float, pg: float, max_growth_mb: float
) -> dict:
    got = state["got"]
    res = {
        "burst_frames_sent": total,
        "burst_frames_received": got,
        "burst_order_errors": state["order_errors"],
        "burst_wall_s": round(wall, 2),
        "burst_frames_per_s": round(got / wall) if wall > 0 else None,
        "burst_sink_rss_growth_mb": round(sg, 1),
        "burst_publisher_rss_growth_mb": round(pg, 1),
    }
    growth_ok = all(not (g > max_growth_mb) for g in (sg, pg))
    res["burst_ok"] = bool(got == total and not state["order_errors"] and growth_ok)
    _say(
        f"burst: sent {total}, received {got} in {wall:.1f} s ({res['burst_frames_per_s']} "
        f"frames/s), order errors {state['order_errors']}; RSS growth sink {sg:+.1f} MiB, "
        f"publisher {pg:+.1f} MiB"
    )
    return res


def soak(argv: list[str]) -> dict:
    ap = Parser(
        prog="fluxdrive soak",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--wall-s", type=float, default=300.0, help="soak wall time (default 300)")
    ap.add_argument("--scenario", default=SOAK_SCENARIO)
    ap.add_argument("--sample-s", type=float, default=5.0, help="RSS sampling period [s]")
    ap.add_argument(
        "--max-growth-mb",
        type=float,
        default=20.0,
        help="allowed RSS growth after warm-up [MiB] (default 20)",
    )
    ap.add_argument(
        "--burst-bag",
        type=Path,
        default=REPO_ROOT / "bags" / "samples" / "paper_2pct_150load",
        help="bag for the burst replay (default: the shipped 2 %% sample)",
    )
    ap.add_argument("--burst-loops", type=int, default=10)
    ap.add_argument("--skip-soak", action="store_true")
    ap.add_argument("--skip-burst", action="store_true")
    ap.add_argument(
        "--write",
        action="store_true",
        help="store the figures in results/benchmarks/soak.json (quoted by docs/performance.md)",
    )
    args = ap.parse_args(argv)
    res: dict = {}
    tmp = Path(tempfile.mkdtemp(prefix="fluxdrive-soak-"))
    try:
        if not args.skip_soak:
            res.update(
                lockstep_soak(
                    scenario_path(args.scenario),
                    args.wall_s,
                    args.sample_s,
                    args.max_growth_mb,
                    tmp,
                )
            )
        if not args.skip_burst:
            res.update(
                burst_replay(
                    args.burst_bag, args.burst_loops, min(args.sample_s, 0.25), args.max_growth_mb
                )
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res["ok"] = all(v for k, v in res.items() if k.endswith("_ok"))
    if args.write:
        from fluxdrive.cli.bench import write_benchmark

        write_benchmark("soak", res)
    return res


def main(argv: list[str] | None = None) -> int:
    try:
        res = soak(sys.argv[1:] if argv is None else argv)
    except (RuntimeError, OSError) as exc:
        print(f"soak: {exc}", file=sys.stderr)
        print(json.dumps({"ok": False, "error": str(exc)}))
        return 1
    print(json.dumps(res))
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    sys.exit(main())
