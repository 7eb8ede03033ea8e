"""Bench bridge across processes: the drive emulator in one process
(`./fluxdrive can-emulator`), the bench_bridge node in another, the ROS side (a probe
answering every PhaseFrame with a DutyCommand) in the test, over python-can's
`udp_multicast` interface on this host (TTL 0: the datagrams never leave the machine; a
port of its own per run, since on Linux a socket bound to a port sees every group joined
on it). The bridge node gets the port through python-can's CAN_CONFIG environment
variable. Checks: frames flow in order, the duties come back applied by the drive, and
stopping the bridge disarms the drive (not its duty watchdog).

The ROS side spins a SingleThreadedExecutor in a background thread (rclpy's
MultiThreadedExecutor busy-waits and starves the other threads on 2 cores)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from fluxdrive.can.bridge import software_bus_endpoint
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("msgpack")  # python-can's udp_multicast needs it

REPO = Path(__file__).resolve().parents[1]
DUTY = (0.52, 0.5, 0.48)


def _multicast_loops_back(group: str, port: int) -> str:
    """'' if a frame sent on the group comes back to another bus in this process."""
    import can

    try:
        rx = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0)
        tx = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0)
    except Exception as exc:  # noqa: BLE001 - any reason means: not here
        return f"udp_multicast bus cannot be opened here: {exc!r}"
    try:
        tx.send(can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False))
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2.0:
            m = rx.recv(0.2)
            if m is not None and m.arbitration_id == 0x7FF:
                return ""
        return "multicast datagrams are not looped back on this host"
    finally:
        rx.shutdown()
        tx.shutdown()


def _stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 20.0) -> str:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate(timeout=5.0)
    return out or ""


def test_emulator_and_bridge_node_in_separate_processes(tmp_path):
    group, port = software_bus_endpoint(os.getpid() ^ time.monotonic_ns())
    why = _multicast_loops_back(group, port)
    if why:
        pytest.skip(why)
    from flux_drive_msgs.msg import DutyCommand, PhaseFrame
    from flux_drive_msgs.srv import Arm
    from fluxdrive_ros import qos, topics

    dom = domain(28)
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=str(dom),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        CAN_CONFIG=json.dumps({"port": port, "hop_limit": 0}),
    )
    emu_log = open(tmp_path / "emulator.err", "w")  # noqa: SIM115 - closed below
    br_log = open(tmp_path / "bridge.out", "w")  # noqa: SIM115
    emu = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fluxdrive.cli",
            "can-emulator",
            "paper_2pct_150load",
            "--interface",
            "udp_multicast",
            "--channel",
            group,
            "--port",
            str(port),
            "--periods",
            "1000000",
            "--lockstep-wait",
            "0.2",
            "--wait-for-host",
            "60",
        ],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=emu_log,
        text=True,
    )
    bridge = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bench_bridge.bridge_node",
            "--ros-args",
            "-p",
            "interface:=udp_multicast",
            "-p",
            f"channel:={group}",
            "-p",
            "stale_timeout_s:=30.0",
            "-p",
            "diagnostics_period_s:=0.5",
            "-p",
            "allowed_commanders:=['*']",
        ],  # the probe plays the graph's controller
        cwd=REPO,
        env=env,
        stdout=br_log,
        stderr=subprocess.STDOUT,
        text=True,
    )
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=dom)
    probe = rclpy.create_node("xproc_probe", context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(probe)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    got: list[tuple[int, tuple[float, ...], bool]] = []
    duty_pub = probe.create_publisher(DutyCommand, topics.DUTY, qos.SAMPLES)

    def on_frame(m: PhaseFrame) -> None:
        got.append((int(m.seq), tuple(m.duty_applied), bool(m.pwm_enabled)))
        duty_pub.publish(DutyCommand(seq=m.seq, duty=list(DUTY), enable=True))

    probe.create_subscription(PhaseFrame, topics.FRAME, on_frame, qos.reader("volatile"))
    arm = probe.create_client(Arm, "/drive/arm")
    emu_out = ""
    try:
        spinner.start()
        assert arm.wait_for_service(timeout_sec=60.0), "bridge node did not come up"
        t0 = time.monotonic()
        while not got and time.monotonic() - t0 < 60.0:
            time.sleep(0.05)
        assert got, "no PhaseFrame from the bridge node"
        res = arm.call(Arm.Request(arm=True), timeout_sec=10.0)
        assert res is not None and res.success, res
        n0 = len(got)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60.0 and sum(1 for g in got[n0:] if g[2]) < 300:
            time.sleep(0.05)
        frames = list(got)
        wall = time.monotonic() - t0
        print(
            f"{len(frames)} frames across 3 processes, {len(frames) - n0} after arming in "
            f"{wall:.2f} s"
        )
        seqs = [g[0] for g in frames]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # in order, no gaps
        on = [g for g in frames[n0:] if g[2]]
        assert len(on) >= 300, "PWM never came on at the drive"
        # the duties applied by the drive are the ones the ROS side sent (2e-5 resolution),
        # after its bootstrap charge (10 periods of upper duties 0 once armed, at D = 1)
        assert all(
            max(abs(a - b) for a, b in zip(g[1], DUTY, strict=True)) < 3e-5 for g in on[2 + 10 :]
        )
        # stop the bridge node: it must disarm the drive on its way out
        br_rc = bridge.send_signal(signal.SIGINT) or bridge.wait(timeout=30.0)
        time.sleep(0.5)
        emu_out = _stop(emu)
    finally:
        ex.shutdown()
        spinner.join(timeout=5.0)
        probe.destroy_node()
        rclpy.shutdown(context=ctx)
        for p in (bridge, emu):
            if p.poll() is None:
                _stop(p, signal.SIGTERM)
        emu_log.close()
        br_log.close()
    lines = [ln for ln in emu_out.splitlines() if ln.startswith("{")]
    assert lines, f"no emulator report; stderr: {(tmp_path / 'emulator.err').read_text()[-2000:]}"
    st = json.loads(lines[-1])
    print(
        {
            k: st[k]
            for k in (
                "periods",
                "duty_applied",
                "disarm_rx",
                "armed",
                "pwm_enabled",
                "fault_codes",
                "stale_periods",
            )
        }
    )
    assert br_rc == 0, (tmp_path / "bridge.out").read_text()[-3000:]
    assert st["duty_applied"] >= 300
    assert st["disarm_rx"] >= 1 and not st["armed"] and not st["pwm_enabled"]
    assert st["fault_codes"] == []  # disarmed by the bridge, not by the duty watchdog
