"""`./fluxdrive tune`: a steady operating point held paced until Ctrl-C.

(a) the hold point is refused above the card's rated torque, with the time after which the
    I2t protection would trip (i2t_limit / (L^2 - 1): 8 s at the paper's 150 %); an accepted
    one becomes the scenario's load ramp (0.16 pu/s from 1 s) and speed;
(b) the real graph, started as a user does, held a few seconds and stopped with SIGINT: the
    plant stops with the PWM off, the command exits 0 and prints its pacing record."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]


def test_hold_point_from_the_card():
    from fluxdrive.drive.scenario import load_scenario, scenario_path
    from fluxdrive_bringup.launch.tune import TUNE_SCENARIO, hold_overrides

    sc = load_scenario(scenario_path(TUNE_SCENARIO))
    assert sc.load_profile_pu[:, 1].max() <= 1.0  # the shipped point: at most rated load
    over, why = hold_overrides(sc, None, 1.5)
    assert over == {}
    i2t = sc.control.i2t_limit_pu2s
    assert f"trip after {i2t / (1.5**2 - 1.0):.1f} s" in why  # 10 / 1.25 = 8.0 s
    assert hold_overrides(sc, 30.0, None)[0] == {}  # below the 40 rpm handover
    over, why = hold_overrides(sc, 120.0, 0.4)
    assert why == ""
    held = load_scenario(scenario_path(TUNE_SCENARIO), overrides=over)
    assert held.speed_profile_rpm[-1, 1] == 120.0
    assert held.load_profile_pu.tolist() == [[0.0, 0.0], [1.0, 0.0], [1.0 + 0.4 / 0.16, 0.4]]


def test_tune_holds_until_sigint(tmp_path):
    env = dict(os.environ)
    env.pop("ROS_DOMAIN_ID", None)
    dom = domain(40)
    cmd = [sys.executable, "-m", "fluxdrive.cli", "tune", "--domain-id", str(dom)]
    proc = subprocess.Popen(
        [*cmd, "--out", str(tmp_path / "tune")],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    try:
        t_end = time.monotonic() + 120.0
        assert proc.stdout is not None
        while time.monotonic() < t_end:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.match(r"\[progress\]\s+([0-9.]+) s simulated", line)
            if m and float(m.group(1)) >= 0.02:  # past 200 frames: the controller answers
                break
        assert any(s.startswith("[progress]") for s in lines), "".join(lines)
        time.sleep(2.0)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    out = "".join(lines) + rest
    assert proc.returncode == 0, out
    assert "stopped before the end of the run: PWM off from frame" in out, out
    rec = json.loads(out.strip().splitlines()[-1])
    assert (rec["speed_rpm"], rec["load_pu"]) == (60.0, 0.8)
    assert rec["frames"] > 200, rec  # it ran paced, with every frame's lateness recorded
    assert {"lateness_p50_periods", "lateness_p99_periods", "watchdog_trips"} <= rec.keys()
