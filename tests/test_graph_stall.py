"""A paced graph tells a late controller from a dead one.  The controller process is
stopped (SIGSTOP) twice, with the plant's watchdog scaled down to WATCHDOG_S of wall time:

- for less than the limit: lateness, not a fault -- the plant waits for the late duty with
  the previous one in effect (time slips: no frame is lost or made without its duty), counts
  it and reports its lateness in the pacing record; the controller goes on in closed loop,
  nothing latched, no frame flagged;
- for more than the limit: silence -- the plant says so in one line and runs with the PWM
  off (frames flagged STATUS_STALE_COMMAND); the controller, continued, finds the PWM
  switched off under it and latches its 'watchdog' fault with one line saying why.

The recorder holds every frame."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain
from test_process_faults import STATUS_STALE_COMMAND, Run, graph_dict, read_frames

pytest.importorskip("rclpy")
# a paced graph whose controller is stopped for wall-time spans against the plant's
# wall-time watchdog: beside another test, its latch once missed the bag
pytestmark = pytest.mark.serial

RATE = 0.2  # simulated seconds per wall second: 2000 frames/s
WATCHDOG_S = 1.5  # the plant's limit (default 1 s): 1.5 s, a loaded machine hiccups for 0.6 s
LATE_STALL_S = 0.25  # less than the limit: late
# more: dead.  At 2000 frames/s a 3 s stop once left the controller silent for over a
# minute after SIGCONT (the test had moved to 1000 frames/s): it must say within seconds
# that it latched
DEAD_STALL_S = 3.0
MODE_CLOSED_LOOP, MODE_FAULT = 3, 4
# the first closed-loop frame of this scenario with the controller settings below (align
# 0.1 s, dwell 0.15 s): the in-process run's, which the paced graph repeats frame for frame
# (a late duty makes the plant wait, not run on); the bag of this test showed 7204 too
CLOSED_LOOP_FROM = 7204
CLOSED_LOOP_MARGIN = 800  # 0.4 s of wall time at RATE: well past the handover
WATCHDOG = 9  # DriveFault.WATCHDOG


def _modes(bag):
    from rosbags.highlevel import AnyReader

    out = {}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/controller_state"]
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            out[int(m.seq)] = int(m.mode)
    return out


def _faults(bag):
    """The bag's DriveFault events: (source, code, latched, frame of the stamp, reason)."""
    from rosbags.highlevel import AnyReader

    out = []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/fault"]
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            k = round((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9) / 1e-4)
            out.append((m.source, int(m.code), bool(m.latched), k, m.reason))
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


def _stall(pid: int, stall_s: float) -> None:
    os.kill(pid, signal.SIGSTOP)
    time.sleep(stall_s)
    os.kill(pid, signal.SIGCONT)


def _runs(ks: list[int]) -> list[list[int]]:
    """Consecutive frame numbers as [first, last] intervals."""
    runs: list[list[int]] = []
    for k in ks:
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    return runs


def test_late_controller_is_counted_a_silent_one_latches(tmp_path):
    bag = tmp_path / "bag"
    g = graph_dict(
        bag,
        duration_s=0.0,
        processes={"controller": "controller", "recorder": "recorder"},
        plant={
            "mode": "paced",
            "rate_factor": RATE,
            "exit_on_done": False,
            "watchdog_s": WATCHDOG_S,
        },
    )
    sc = _ideal_bench_scenario(tmp_path)  # (a shorter start-up keeps the test short)
    for nd in g["nodes"]:
        if "scenario" in nd["parameters"]:
            nd["parameters"]["scenario"] = sc
    # the paced plant switches the PWM off only for a silent controller: latch the first
    next(nd for nd in g["nodes"] if nd["name"] == "controller")["parameters"].update(
        align_time_s=0.1, handover_dwell_s=0.15, max_resyncs=0
    )
    run = Run(g, domain(11), tmp_path)
    run.thread = threading.Thread(
        target=lambda: setattr(run, "code", run.launcher.run(timeout=400)), daemon=True
    )
    run.start()
    # closed loop from frame CLOSED_LOOP_FROM on (kernels compile first: minutes on a loaded
    # machine); the late stall comes CLOSED_LOOP_MARGIN frames after it
    run.wait_frames(CLOSED_LOOP_FROM + CLOSED_LOOP_MARGIN, timeout=400)
    pid = run.pid("controller")
    at, k_late = len(run.lines), run.frames()
    _stall(pid, LATE_STALL_S)
    run.wait_frames(run.frames() + 1500)
    late_lines = "\n".join(run.lines[at:])
    at, k_dead = len(run.lines), run.frames()
    _stall(pid, DEAD_STALL_S)
    plant_line = run.wait_line(
        rf"watchdog: no duty command at all for [0-9.]+ s of wall time \(watchdog_s "
        rf"{WATCHDOG_S:g}; the controller is dead or stopped, not late\); PWM off from frame "
        r"(\d+)",
        after=at,
    )
    t_cont = time.monotonic()
    latched = (
        r"watchdog: the power stage's watchdog switched the PWM off at frame \d+: no duty "
        r"command from this controller for its wall-time limit \(stopped or dead, not "
        r"late\); PWM off \(latched\)"
    )
    # it answers the frames queued while it stood still first: under load that is slow; or
    # its DDS reader holds every frame behind one dropped during the stop, and it says so
    # (docs/graph.md, "Limit at high frame rates")
    held = r"no frame for [0-9.]+ s of wall time after frame \d+"  # 5.0 s, later under load
    m = run.wait_line(f"(?P<latched>{latched})|(?P<held>{held})", after=at, timeout=90)
    if m["held"]:
        try:
            run.wait_line(latched, after=at, timeout=60)
        except pytest.fail.Exception:
            run.launcher.stop()
            run.join()
            pytest.xfail(
                "the documented limit at 2000 frames/s: the resumed controller's DDS reader "
                "held every frame behind one dropped during its stop, and it said so; the "
                "plant had switched the PWM off"
            )
    after_cont_s = time.monotonic() - t_cont
    run.wait_frames(run.frames() + 2000)
    run.launcher.stop()
    code = run.join()
    out = run.text()
    assert code == 0, out
    assert "watchdog" not in late_lines and "latched" not in late_lines, late_lines
    pacing = json.loads(re.findall(r"pacing (\{.*\})", out)[-1])
    print(pacing)
    seqs, pwm, flags, _ = read_frames(bag)
    modes = _modes(bag)
    n = len(seqs)
    assert seqs == list(range(n)), "the bag lost frames"
    stale = _runs([k for k, f in zip(seqs, flags, strict=True) if f & STATUS_STALE_COMMAND])
    # the late stall: every frame made with its own duty, closed loop on both sides
    assert not [r for r in stale if k_late - 100 <= r[1] and r[0] < k_dead], stale
    assert modes[k_late - 30] == MODE_CLOSED_LOOP and modes[k_dead] == MODE_CLOSED_LOOP
    assert MODE_FAULT not in [modes[k] for k in range(k_late, k_dead) if k in modes]
    # the dead one: PWM off from the watchdog's frame on
    k_off = int(plant_line.group(1))
    a, b = next(r for r in stale if r[1] >= k_dead)
    assert a == k_off and not any(pwm[a : b + 1]), (a, k_off, b)
    assert modes[max(modes)] == MODE_FAULT
    # each side's fault is one DriveFault in the bag: the plant's watchdog (not latched, at
    # the frame it switched off; a "back" event only once duties answer live frames again)
    # and the controller's latch
    events = _faults(bag)
    plant = [e for e in events if e[0] == "/plant"]
    assert plant[0][1:4] == (WATCHDOG, False, k_off), events
    assert plant[0][4].startswith("watchdog: no duty command at all for"), events
    assert [e[1] for e in plant] in ([WATCHDOG], [WATCHDOG, 0]), events
    ctrl = [e[1:3] for e in events if e[0] == "/controller"]
    assert ctrl == [(WATCHDOG, True)], events
    # (how far the latched controller has come by the end: it may still be answering the
    # frames queued while it stood still -- the plant says "duty commands back" only once
    # it answers a frame still to come)
    print(f"latched {after_cont_s:.2f} s after SIGCONT; answered up to {max(modes)} of {n}")
    # the record: the late duty of the first stall and its lateness, one trip
    trips = [ln for ln in out.splitlines() if "watchdog" in ln or "commands back" in ln]
    assert pacing["watchdog_trips"] == 1, "\n".join(trips)
    assert pacing["late_duties"] >= 1
    assert pacing["duty_lateness_max_periods"] >= 0.5 * LATE_STALL_S * RATE * 1e4
    assert pacing["duty_lateness_p50_periods"] <= pacing["duty_lateness_p99_periods"]
