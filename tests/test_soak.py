"""Load check, short version: `./fluxdrive soak` on a ~10 s lockstep graph run
and a 6-pass unpaced burst replay.  Every message of every topic in the bag (counts from
the mcap summary = periods, and equal to the recorder's metadata.yaml), RSS growth of the
graph after warm-up under 20 MiB, burst received == sent in order with flat memory.
The 5-minute soak is the same command with its defaults (figures in README)."""

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
