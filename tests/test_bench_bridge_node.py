"""bench_bridge ROS node, in-process with the drive emulator on a virtual CAN bus:
PhaseFrames on /drive/frame, Arm service, duties -> DUTY_CMD, /diagnostics.

A SingleThreadedExecutor spins in a background thread: rclpy's MultiThreadedExecutor
busy-waits while a mutually exclusive group is busy and starved the CAN threads (300
round trips took 20-40 s instead of 0.5 s)."""

from __future__ import annotations

import os
import threading
import time

import pytest

rclpy = pytest.importorskip("rclpy")


def test_bridge_node_smoke():
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import can
    from bench_bridge.bridge_node import BenchBridgeNode
    from diagnostic_msgs.msg import DiagnosticArray
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.sim import DriveSetup
    from rclpy.parameter import Parameter
    from test_bench_bridge import short_2pct

    from flux_drive_msgs.msg import DutyCommand, PhaseFrame
    from flux_drive_msgs.srv import Arm

    ch = new_virtual_channel()
    emu_bus = can.Bus(interface="virtual", channel=ch, fd=True)
    emu = DriveEmulator(DriveSetup(short_2pct(0.5)), emu_bus, lockstep=True, lockstep_wait_s=0.2)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0")) % 100 + 1)
    node = BenchBridgeNode(
        context=ctx,
        parameter_overrides=[
            Parameter("channel", value=ch),
            Parameter("stale_timeout_s", value=30.0),
            Parameter("diagnostics_period_s", value=0.2),
            Parameter("allowed_commanders", value=["*"]),
        ],
    )  # the probe plays the graph (access)
    probe = rclpy.create_node("probe", context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    got, diags = [], []
    duty_pub = probe.create_publisher(DutyCommand, "/drive/duty", 100)

    def on_frame(m):
        got.append(m.seq)
        d = DutyCommand(seq=m.seq, duty=[0.52, 0.5, 0.48], enable=True)
        duty_pub.publish(d)

    probe.create_subscription(PhaseFrame, "/drive/frame", on_frame, 100)
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    arm = probe.create_client(Arm, "/drive/arm")
    try:
        spinner.start()
        assert arm.wait_for_service(timeout_sec=5.0)
        res = arm.call(Arm.Request(arm=True), timeout_sec=5.0)
        assert res is not None and res.success
        emu.start(300)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60.0 and len(got) < 300:
            time.sleep(0.05)
        print(f"300 frames round trip in {time.monotonic() - t0:.2f} s; {emu.stats}")
        assert got[:300] == list(range(300))
        assert emu.stats.duty_applied > 250, emu.stats
        assert emu.armed and emu.pwm_enabled, (emu.stats, node.bridge.diagnostics())
        while time.monotonic() - t0 < 60.0 and not diags:
            time.sleep(0.05)
        kv = {k.key: k.value for k in diags[-1].status[0].values}
        assert kv["malformed"] == "0" and int(kv["duty_tx_enabled"]) > 0
    finally:
        emu.stop()
        ex.shutdown()  # stop spinning before the nodes go away
        spinner.join(timeout=5.0)
        node.destroy_node()  # disarms
        emu._drain(0.1)
        assert not emu.armed
        probe.destroy_node()
        rclpy.shutdown(context=ctx)
        emu_bus.shutdown()


def test_bridge_node_decimation_parameter_and_drive_check():
    """`decimation` is a declared parameter (range checked); it reaches the bridge and
    ARM_MODE, and a drive whose STATUS reports another D is refused: the Arm service fails
    with the reason, the drive counts the ARM_MODE it disagrees with, /diagnostics is an
    ERROR once the mismatch latched a fault."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import can
    from bench_bridge.bridge_node import BenchBridgeNode
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.sim import DriveSetup
    from rclpy.exceptions import InvalidParameterValueException
    from rclpy.parameter import Parameter
    from test_bench_bridge import short_2pct

    from flux_drive_msgs.srv import Arm

    ch = new_virtual_channel()
    emu_bus = can.Bus(interface="virtual", channel=ch, fd=True)
    emu = DriveEmulator(DriveSetup(short_2pct(0.1)), emu_bus, lockstep=False)  # FD, D = 1
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0")) % 100 + 1)
    with pytest.raises(InvalidParameterValueException, match="decimation out of range"):
        BenchBridgeNode(
            context=ctx,
            parameter_overrides=[
                Parameter("channel", value=ch),
                Parameter("decimation", value=300),
            ],
        )
    node = BenchBridgeNode(
        context=ctx,
        parameter_overrides=[
            Parameter("channel", value=ch),
            Parameter("decimation", value=4),
            Parameter("diagnostics_period_s", value=0.1),
            Parameter("allowed_commanders", value=["*"]),
        ],
    )
    probe = rclpy.create_node("probe", context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    diags = []
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    arm = probe.create_client(Arm, "/drive/arm")
    try:
        desc = node.describe_parameter("decimation")
        assert desc.read_only and desc.integer_range[0].to_value == 255
        assert "[periods]" in desc.description
        assert node.bridge.layout == "fd" and node.bridge.decimation == 4
        spinner.start()
        assert arm.wait_for_service(timeout_sec=5.0)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10.0 and emu.stats.layout_mismatch == 0:
            emu._drain(0.05)  # the node's ARM_MODE asks for D = 4
        assert emu.stats.layout_mismatch >= 1
        emu._send_status()  # the drive says D = 1
        while time.monotonic() - t0 < 10.0 and not node.bridge.drive_mismatch:
            time.sleep(0.02)
        res = arm.call(Arm.Request(arm=True), timeout_sec=5.0)
        assert res is not None and not res.success and "D=1" in res.message, res
        emu._send_status()
        while time.monotonic() - t0 < 10.0 and not node.bridge.fault:
            time.sleep(0.02)
        assert "layout mismatch" in node.bridge.fault
        n0 = len(diags)
        while time.monotonic() - t0 < 20.0 and len(diags) < n0 + 2:
            time.sleep(0.05)
        st = diags[-1].status[0]
        kv = {k.key: k.value for k in st.values}
        assert st.level == DiagnosticStatus.ERROR and "layout mismatch" in st.message
        assert kv["decimation"] == "4" and kv["layout_mismatch"] == "2"
    finally:
        ex.shutdown()
        spinner.join(timeout=5.0)
        node.destroy_node()
        probe.destroy_node()
        rclpy.shutdown(context=ctx)
        emu_bus.shutdown()
