"""Live tuning on a running lockstep graph: the observer's cut-off and the controller's
current-loop bandwidth changed mid-run through the parameter services (as `./fluxdrive
param set` does).  Each node logs the sample from which the change holds; the
recorded estimates and controller outputs then equal an in-process run with the same
changes at those samples -- and differ from the unchanged run.  Out-of-range and
design-refused values are rejected with a reason and change nothing.

The run ends on a condition, not a count: the graph may run for up to DURATION_MAX_S of drive
time and is stopped once the changes have landed and MORE_FRAMES frames have followed them
(on a loaded machine a fixed 3 s run could end before the change arrived)."""

from __future__ import annotations

import dataclasses
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml"
DURATION_MAX_S = 30.0  # the graph's scenario: an upper bound, the test stops it earlier
MORE_FRAMES = 3000  # frames run after the later change before the stop


def _reference(sc, changes: dict[int, list], end: int | None = None):
    """The in-process loop (fluxdrive.drive.sim.LoopRun) with parameter rows replaced
    at given samples: changes = {k: [callable(ds, cp, obs_params), ...]}; its first `end`
    samples (all by default)."""
    from fluxdrive.drive.sim import DriveSetup, LoopRun

    run = LoopRun(DriveSetup(sc))
    end = run.n if end is None else end
    for b in sorted([*changes, end]):
        if b > run.k:
            run.advance(b)
        for fn in changes.get(b, []):
            fn(run.ds, run.cp, run.obs_params)
    return run.frames[:end], run.est[:, :end], run.ctrl[:end]


def test_live_parameters_take_effect_exactly_and_bad_values_are_rejected(tmp_path):
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive_bringup.inspect.commands import Session, set_param
    from fluxdrive_bringup.launch.launcher import Launcher
    from fluxdrive_bringup.launch.runs import graph_for_scenario, result_from_bag, shorten

    dom = domain(18)
    sc = load_scenario(SCENARIO)
    shorten(sc, DURATION_MAX_S)
    bag = tmp_path / "bag"
    # a long settling delay: the parameter client discovers the services before frame 0
    g = graph_for_scenario(SCENARIO, sc, bag, "composed", DURATION_MAX_S, dom, start_delay_s=2.5)
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp_path / "logs")
    codes = []
    th = threading.Thread(target=lambda: codes.append(launcher.run(timeout=300)), daemon=True)
    th.start()
    s = Session(domain_id=dom, wait_s=20.0)

    def frames() -> int:
        return launcher.progress[0] if launcher.progress is not None else 0

    def wait_frames(k: int, timeout: float = 120.0) -> None:
        t_end = time.monotonic() + timeout
        while frames() < k and th.is_alive() and time.monotonic() < t_end:
            time.sleep(0.02)
        assert frames() >= k, f"the graph did not reach frame {k} (at {frames()})"

    def first_get(node: str, name: str, timeout_s: float = 180.0):
        """The value, once the process answers: a server is found as its node is built,
        but answers once every node of the process is built and it spins (at load 20
        that was more than a call's 5 s after the first was found)."""
        t_end = time.monotonic() + timeout_s
        while True:
            try:
                return _get(s, node, [name])[0][1]
            except TimeoutError:
                if time.monotonic() > t_end or not th.is_alive():
                    raise

    try:
        # services up (the process spins), then wait for the run to be under way
        from fluxdrive_bringup.inspect.commands import _get

        assert first_get("/obs/flux_measured", "cutoff_hz") == 100.0
        assert first_get("/controller", "current_bandwidth_hz") == 1000.0
        wait_frames(5000)

        ok, reason, _ = set_param(s, "/obs/flux_measured", "cutoff_hz", "50.0")
        assert ok, reason
        ok, reason, _ = set_param(s, "/controller", "current_bandwidth_hz", "500")  # int ok
        assert ok, reason

        # rejected, each with its reason; nothing changes
        ok, reason, _ = set_param(s, "/obs/flux_measured", "cutoff_hz", "5000.0")
        assert not ok and "cutoff_hz" in reason and "2000" in reason, reason
        ok, reason, _ = set_param(s, "/obs/flux_measured", "voltage_source", "bogus")
        assert not ok and "measured" in reason, reason
        ok, reason, _ = set_param(s, "/controller", "current_bandwidth_hz", "3000.0")
        # the descriptor's range is the controller's rule (a quarter of the PWM frequency)
        assert not ok and "out of range" in reason and "2500" in reason, reason
        ok, reason, _ = set_param(s, "/controller", "handback_rpm", "45.0")
        assert not ok and "handback" in reason, reason
        assert _get(s, "/obs/flux_measured", ["cutoff_hz"])[0][1] == 50.0
        assert _get(s, "/controller", ["current_bandwidth_hz"])[0][1] == 500.0
        # each node logs the sample the change holds from (rclpy keeps no reason of a
        # successful set): wait for both lines, then for MORE_FRAMES frames after them
        log = tmp_path / "logs" / "drive.log"
        k: dict[str, int] = {}
        t_end = time.monotonic() + 60
        while len(k) < 2 and time.monotonic() < t_end:
            text = log.read_text() if log.exists() else ""
            for key, pattern in (
                ("obs", r"\{'cutoff_hz': 50.0\}: applied from frame (\d+)"),
                ("ctl", r"\{'current_bandwidth_hz': 500.0\}: applied from sample (\d+)"),
            ):
                found = re.search(pattern, text)
                if found:
                    k[key] = int(found.group(1))
            time.sleep(0.05)
        assert len(k) == 2, f"the nodes did not log where the changes hold from: {k}"
        k_obs, k_ctl = k["obs"], k["ctl"]
        m = max(k_obs, k_ctl) + MORE_FRAMES
        wait_frames(m + 10)  # lockstep: every reader is done with frame m - 1 by then
    finally:
        s.close()
        launcher.stop()
        th.join(timeout=180)
    assert codes == [0], tmp_path / "logs"
    assert 5000 <= k_obs and 5000 <= k_ctl, (k_obs, k_ctl)

    # the recorded run == the in-process loop with the same changes at the same samples
    card = sc.machine
    i_obs = list(sc.observers).index("flux_measured")

    def obs_change(ds, cp, op):
        op[i_obs] = sc.observers["flux_measured"].with_overrides(cutoff_hz=50.0).to_params(card)

    def ctl_change(ds, cp, op):
        cp[:] = dataclasses.replace(sc.control, current_bandwidth_hz=500.0).to_params(card)

    changes: dict[int, list] = {}
    changes.setdefault(k_obs, []).append(obs_change)
    changes.setdefault(k_ctl, []).append(ctl_change)
    # the frames up to the stop (the plant's last one, PWM off at the stop, is not the loop's)
    ref_f, ref_e, ref_c = _reference(sc, changes, m)
    res, arr = result_from_bag(bag, load_scenario(SCENARIO), DURATION_MAX_S)
    assert arr["n"] > m, (arr["n"], m)
    for got in (res.frames[:m], res.est[:, :m], res.ctrl[:m]):
        assert not np.isnan(got).any()  # every sample up to the stop is in the bag
    assert np.array_equal(res.frames[:m], ref_f)
    assert np.array_equal(res.est[:, :m], ref_e)
    assert np.array_equal(res.ctrl[:m], ref_c)

    # ... and the changes did something: estimates and voltages leave the unchanged run
    _, base_e, base_c = _reference(sc, {}, m)
    k0 = min(k_obs, k_ctl)
    assert np.array_equal(res.est[:, :k0], base_e[:, :k0])
    assert not np.array_equal(res.est[i_obs, k_obs:m], base_e[i_obs, k_obs:])
    assert not np.array_equal(res.ctrl[k_ctl:m], base_c[k_ctl:])


def test_paced_plant_watchdog_switches_pwm_off_without_a_controller(tmp_path):
    """Paced mode with no controller in the graph: the plant holds frame 2 waiting for
    duty(0), then its watchdog lets it run on at the wall-clock rate with the PWM off, every
    frame flagged as run on a stale command; the recorder still gets every frame."""
    from fluxdrive_bringup.launch.launcher import Graph, Launcher, NodeSpec
    from rosbags.highlevel import AnyReader

    dom = domain(19)
    bag = tmp_path / "bag"
    g = Graph(
        name="paced",
        domain_id=dom,
        nodes=[
            NodeSpec(
                name="plant",
                node="plant",
                process="drive",
                parameters={
                    "scenario": str(SCENARIO),
                    "mode": "paced",
                    "rate_factor": 0.2,
                    "duration_s": 0.05,
                    "wait_frame_subscribers": 1,
                    "wait_duty_publishers": 0,
                    "start_delay_s": 0.0,
                    "first_duty_timeout_s": 5.0,  # not the 30 s default: the same hold, shorter
                },
            ),
            NodeSpec(
                name="recorder",
                node="recorder",
                process="drive",
                parameters={"bag_dir": str(bag), "topics": ["/drive/frame"]},
            ),
        ],
    )
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp_path / "logs")
    t0 = time.monotonic()
    assert launcher.run(timeout=60) == 0
    assert time.monotonic() - t0 > 5.0  # held ~5 s for a first duty command
    log = (tmp_path / "logs" / "drive.log").read_text()
    assert "watchdog: no duty command" in log and "PWM off from frame 2" in log
    assert "(first_duty_timeout_s 5; " in log
    with AnyReader([bag]) as r:
        conns = [c for c in r.connections if c.topic == "/drive/frame"]  # not the settings
        frames = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    assert [f.seq for f in frames] == list(range(500))
    assert not any(f.pwm_enabled for f in frames)
    assert all(f.status_flags & 16 for f in frames[2:])  # STATUS_STALE_COMMAND
    assert all(f.status_flags & 2 for f in frames)  # STATUS_SIMULATED
