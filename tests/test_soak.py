"""Load check, short version: `./fluxdrive soak` on a ~10 s lockstep graph run
and a 6-pass unpaced burst replay.  Every message of every topic in the bag (counts from
the mcap summary = periods, and equal to the recorder's metadata.yaml), RSS growth of the
graph (each process after its own warm-up) under 20 MiB, burst received == sent in order
with flat memory.  The 5-minute soak is the same command with its defaults (figures in README)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from fluxdrive.io.bagio import bag_counts
from fluxdrive.io.topics import FRAME

pytest.importorskip("rclpy")
# RSS growth and burst throughput of whole graphs: measured with the machine to itself
pytestmark = pytest.mark.serial
REPO = Path(__file__).resolve().parents[1]


def test_soak_and_burst_lose_nothing_and_do_not_grow():
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "fluxdrive.cli",
            "soak",
            "--wall-s",
            "6",
            "--sample-s",
            "1",
            "--burst-loops",
            "4",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert p.returncode == 0, p.stderr[-3000:] + p.stdout[-2000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    print(res)
    assert res["ok"] and res["soak_ok"] and res["burst_ok"]
    assert res["lost"] == {} and res["metadata_mismatch"] == {}
    # plant frame + truth + controller state + 2 estimates per period, plus /clock etc.
    assert res["messages"] >= 5 * res["periods"]
    assert res["rss_samples"] >= 4 and res["rss_growth_mb"] <= 20.0
    # every frame of the shipped sample bag, four passes
    sample_frames = bag_counts(REPO / "bags" / "samples" / "paper_2pct_150load")[0]
    assert res["burst_frames_received"] == res["burst_frames_sent"] == 4 * sample_frames[FRAME]
    assert res["burst_order_errors"] == 0


def _writer_run(leak_mib_per_s: float) -> dict[str, list[tuple[float, float]]]:
    """100 s sampled every second: the drive flat at 200 MiB from t = 0; the bag writer
    starts at t = 30 (after the run's 20 s warm-up), grows 86 -> 115 MiB over its first
    10 s of start-up, then stays flat, or grows by `leak_mib_per_s` from t = 40."""
    drive = [(float(t), 200.0) for t in range(101)]
    writer = [
        (float(t), 86.0 + 2.9 * (t - 30) if t < 40 else 115.0 + leak_mib_per_s * (t - 40))
        for t in range(30, 101)
    ]
    return {"drive[1]": drive, "bagwriter[2]": writer}


def test_a_late_process_start_up_is_not_growth_but_its_leak_is():
    from fluxdrive_bringup.measure.soak import RssSampler, graph_growth

    flat = _writer_run(0.0)
    # the summed series after the run's warm-up (t >= 20) counts the writer's start-up:
    # first third t = 20..46, median (14th) = 200 + 86 + 3 * 2.9; last 315: +20.3 > 20
    old = RssSampler(1.0)
    old.samples = [(t, m + dict(flat["bagwriter[2]"]).get(t, 0.0)) for t, m in flat["drive[1]"]]
    assert old.warmup_s() == 20.0
    assert old.growth_mb() == pytest.approx((294.7, 315.0, 20.3))
    # each process from its own warm-up (the writer from t = 50): nothing grew
    start, end, growth, per = graph_growth(flat, 20.0)
    assert (start, end, growth) == (315.0, 315.0, 0.0)
    assert per == {"drive[1]": (200.0, 200.0, 0.0), "bagwriter[2]": (115.0, 115.0, 0.0)}
    # a leak of 1 MiB/s in the late writer: its samples t = 50..100, thirds of 17, medians
    # at t = 58 and t = 92 -> 133 and 167 MiB, +34 MiB, over the 20 MiB limit
    start, end, growth, per = graph_growth(_writer_run(1.0), 20.0)
    assert per["bagwriter[2]"] == (133.0, 167.0, 34.0)
    assert (start, end, growth) == (333.0, 367.0, 34.0)
    # a process seen for less than its warm-up plus three samples is not judged
    _, _, growth, per = graph_growth({**flat, "late[3]": [(99.0, 50.0), (100.0, 90.0)]}, 20.0)
    assert growth == 0.0 and all(g != g for g in per["late[3]"])


def test_recorder_backpressure_holds_the_graph_and_loses_nothing(tmp_path):
    """A bag writer behind the graph holds the lockstep loop instead of growing the
    recorder's buffer (max_backlog_mb 0.5); every message still lands in the bag.  The
    writer is made to fall behind for certain, whatever the machine's speed: it is stopped
    (SIGSTOP) once the graph runs, until the recorder says it holds, then resumed."""
    import signal

    import psutil
    from fluxdrive.io.bagio import bag_counts
    from ros_domains import domain
    from test_process_faults import Run, graph_dict

    bag = tmp_path / "bag"
    n = 10_000
    g = graph_dict(bag, duration_s=n / 10_000, processes={}, recorder={"max_backlog_mb": 0.5})
    run = Run(g, domain(35), tmp_path).start()
    run.wait_frames(100, timeout=400)  # running: the writer has opened the bag (kernels first)
    drive = psutil.Process(run.pid("drive"))
    (writer,) = [
        p for p in drive.children(recursive=True) if "fluxdrive.cli.bagwriter" in p.cmdline()
    ]
    writer.send_signal(signal.SIGSTOP)
    try:
        run.wait_line("holding the callbacks until it catches up", timeout=300)
    finally:
        writer.send_signal(signal.SIGCONT)
    assert run.join(timeout=300) == 0, run.text()
    mc, meta = bag_counts(bag)
    assert mc["/drive/frame"] == n and mc["/drive/controller_state"] == n
    assert all(mc[t] == n for t in mc if t.endswith("/estimate"))
    assert mc == meta
    assert "the writer's backpressure held the callbacks" in run.text()
