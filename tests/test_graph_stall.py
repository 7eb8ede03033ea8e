"""A paced graph survives a stalled controller: the controller process is stopped
(SIGSTOP) for 0.2 s, 1 s and 3 s of wall time and continued.  Each time the plant's watchdog
switches the PWM off (frames flagged STATUS_STALE_COMMAND), the controller finds the lost
interval when it resumes and comes back -- flying on the estimate while the rotor turns
above the handover speed, else through align / I-f -- to closed loop on its own:
no latched fault; the recorder holds every frame."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest
from test_process_faults import STATUS_STALE_COMMAND, Run, domain, graph_dict, read_frames

pytest.importorskip("rclpy")

RATE = 0.1  # simulated seconds per wall second: 1000 frames/s
# (a 3 s stall leaves 3000 frames and as many estimates for the stopped controller's
# DDS readers to take back on SIGCONT; at 2000 frames/s that backlog now and then left the
# controller without any frame for over a minute on the loaded machine)
WATCHDOG_PERIODS = 100  # 100 ms of wall time at RATE
MODE_CLOSED_LOOP, MODE_FAULT = 3, 4


def _modes(bag):
    from rosbags.highlevel import AnyReader

    out = {}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/controller_state"]
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            out[int(m.seq)] = int(m.mode)
    return out


def _ideal_bench_scenario(tmp_path):
    """The demo scenario on the ideal bench: its sensorless start hands over within about
    a second (on the scenario's non-ideal bench only later; docs/engine.md).  The brake
    ramps as fast as the scenario's but stops at 0.3 pu (2.6 s) instead of 1.5 pu: a
    restart through I-f carries at most its 0.6 pu current -- past that the restart is
    refused ("start-up failed" after handover_timeout_s, tests/test_startup_timeout.py)."""
    import yaml
    from test_process_faults import SCENARIO

    raw = yaml.safe_load(open(SCENARIO).read())
    raw["machine"] = str((Path(SCENARIO).parent / raw["machine"]).resolve())
    raw["bench"] = {}
    raw["load_pu"] = [[0.0, 0.0], [1.0, 0.0], [2.6, 0.3]]  # the scenario's 0.19 pu/s ramp
    p = tmp_path / "ideal_bench.yaml"
    p.write_text(yaml.safe_dump(raw))
    return str(p)


def test_stalled_controller_recovers_in_a_paced_graph(tmp_path):
    bag = tmp_path / "bag"
    g = graph_dict(
        bag,
        duration_s=0.0,
        processes={"controller": "controller", "recorder": "recorder"},
        plant={
            "mode": "paced",
            "rate_factor": RATE,
            "exit_on_done": False,
            "watchdog_periods": WATCHDOG_PERIODS,
        },
    )
    # this loaded 2-core machine also stalls the controller for 100 ms now and then by itself
    # (each a lost interval too): no limit on their number here
    # (a shorter start-up than the scenario's keeps the test short)
    sc = _ideal_bench_scenario(tmp_path)
    for nd in g["nodes"]:
        if "scenario" in nd["parameters"]:
            nd["parameters"]["scenario"] = sc
    next(nd for nd in g["nodes"] if nd["name"] == "controller")["parameters"].update(
        max_resyncs=1000, align_time_s=0.1, handover_dwell_s=0.15
    )
    run = Run(g, domain(11), tmp_path)
    run.thread = threading.Thread(
        target=lambda: setattr(run, "code", run.launcher.run(timeout=400)), daemon=True
    )
    run.start()
    run.wait_frames(11000, timeout=180)  # closed loop from about frame 9000
    pid = run.pid("controller")
    stalls = []
    for stall_s in (0.2, 1.0, 3.0):
        at = len(run.lines)
        k0 = run.frames()
        os.kill(pid, signal.SIGSTOP)
        time.sleep(stall_s)
        os.kill(pid, signal.SIGCONT)
        # the controller resumes flying on the estimate while the braked rotor still turns
        # above the handover speed, through align / I-f once it has slowed below it
        run.wait_line(
            r"interval lost; (restarting through align / I-f|flying restart on "
            r"the estimate)",
            after=at,
        )
        run.wait_line(
            r"PWM back at frame \d+ after \d+ lost period\(s\) from frame \d+; "
            r"(restarting through align / I-f|flying restart on the estimate)",
            after=at,
        )
        stalls.append((stall_s, k0))
        run.wait_line(r"closed loop again at frame \d+", after=at, timeout=120)
        run.wait_frames(run.frames() + 1000)
    run.launcher.stop()
    code = run.join()
    out = run.text()
    assert code == 0, out
    assert "latched" not in out, out
    seqs, pwm, flags, counts = read_frames(bag)
    modes = _modes(bag)
    n = len(seqs)
    assert seqs == list(range(n)), "the bag lost frames"
    stale = [k for k, f in zip(seqs, flags, strict=True) if f & STATUS_STALE_COMMAND]
    runs = []  # the stale intervals, [first, last]
    for k in stale:
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    runs = [r for r in runs if r[1] < n - 1]  # (the plant's final PWM-off period)
    print(f"{n} frames; stale intervals {runs}; stalls {stalls}")
    assert len(runs) >= 3, runs
    for stall_s, k0 in stalls:  # the stale interval each stall caused
        a, b = next(r for r in runs if r[1] >= k0)
        assert not any(pwm[a : b + 1])
        # the watchdog bridges WATCHDOG_PERIODS; the stall lasts stall_s * RATE * 1e4 periods
        assert (b - a + 1) >= 0.5 * stall_s * RATE * 1e4 - WATCHDOG_PERIODS, (stall_s, a, b)
        # closed loop before each stall (the machine's own hiccups may add stale
        # intervals elsewhere, e.g. during the start)
        assert modes[a - 30] == MODE_CLOSED_LOOP
    assert MODE_FAULT not in modes.values()
    assert modes[max(modes)] == MODE_CLOSED_LOOP  # and again after the last
