"""`run` never hangs on a silent graph: a graph with a plant must show its first frame within
start_timeout_s and then at least one frame per wall second over any stall_timeout_s; else the
launcher stops it (continuing SIGSTOPped processes first, so they stop cleanly) with one line
naming the phase, the process silent the longest and the newest warning.  The probe's
recorder stalled 45 s and an observer stalled at load each left `run` hung for 12-15 min;
here the drive process is SIGSTOPped with the limit scaled down to 4 s."""

from __future__ import annotations

import io
import os
import signal
import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml"


def test_a_stopped_drive_stops_the_run_with_one_line(tmp_path):
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive_bringup.launch.launcher import Launcher
    from fluxdrive_bringup.launch.runs import graph_for_scenario

    dom = domain(37)
    sc = load_scenario(SCENARIO)
    sc.observers = {k: sc.observers[k] for k in ("flux_measured",)}
    g = graph_for_scenario(SCENARIO, sc, None, "composed", 300.0, dom)
    g.stall_timeout_s, g.stop_timeout_s = 4.0, 5.0
    out = io.StringIO()
    launcher = Launcher(g, out=out, quiet=True, progress=False, log_dir=tmp_path / "logs")
    codes: list[int] = []
    th = threading.Thread(target=lambda: codes.append(launcher.run(timeout=240)), daemon=True)
    th.start()
    t_end = time.monotonic() + 120
    while (launcher.progress is None or launcher.progress[0] < 2000) and time.monotonic() < t_end:
        time.sleep(0.05)
    assert launcher.progress is not None, f"the graph did not start; {out.getvalue()}"
    pid = launcher.procs[0].popen.pid
    os.kill(pid, signal.SIGSTOP)
    t_stop = time.monotonic()
    th.join(timeout=120)
    took = time.monotonic() - t_stop
    text = out.getvalue()
    print(text)
    assert not th.is_alive(), "run hung"
    assert codes == [1]
    lines = [ln for ln in text.splitlines() if "the graph is stuck" in ln]
    assert len(lines) == 1
    assert "run phase: 0 frames in the last stall_timeout_s = 4 s" in lines[0]
    assert "silent longest: process 'drive'" in lines[0]
    print(f"stopped {took:.1f} s after the SIGSTOP")
    assert launcher.procs[0].popen.poll() is not None  # continued, then stopped
