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
from ros_domains import domain

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
    rclpy.init(context=ctx, domain_id=domain(44))
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
        # the drive answers its bus between periods until armed (its parameters first)
        armed = threading.Event()
        server = threading.Thread(target=emu.serve, args=(armed,), kwargs={"until_armed": True})
        server.start()
        res = arm.call(Arm.Request(arm=True), timeout_sec=10.0)
        armed.set()
        server.join()
        assert res is not None and res.success, res
        assert node.bridge.diagnostics()["params_verified"]
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
        emu.step()  # the drive's interrupt takes the ARM_MODE
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
    sc = short_2pct(0.1)  # the drive: FD, D = 1, a STATUS every period
    emu = DriveEmulator(DriveSetup(sc), emu_bus, lockstep=False, status_period_s=sc.machine.ts_s)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain(45))
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
            emu.step()  # the drive's interrupt takes it
        assert emu.stats.layout_mismatch >= 1  # and its STATUS says D = 1
        while time.monotonic() - t0 < 10.0 and not node.bridge.drive_mismatch:
            time.sleep(0.02)
        res = arm.call(Arm.Request(arm=True), timeout_sec=5.0)
        assert res is not None and not res.success and "D=1" in res.message, res
        emu.step()  # the next STATUS
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


def test_bridge_node_publishes_every_fault_and_marks_parameter_changes():
    """In a namespace (/bench_a: every name relative), on a python-can virtual bus with the
    drive emulator: the supervisor's own stale-data fault and its reset, and a fault the
    drive reports in its FAULT frame and its clearing, are each one DriveFault on
    /bench_a/drive/fault (code, latched, source, reason); a parameter set through the
    parameter service is a ParameterMarker on /bench_a/drive/param_marker at the next
    sample."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import can
    from bench_bridge.bridge_node import BenchBridgeNode
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.plant import FR_IA
    from fluxdrive.drive.sim import DriveSetup
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    from test_bench_bridge import short_2pct

    from flux_drive_msgs.msg import DriveFault, ParameterMarker, PhaseFrame
    from flux_drive_msgs.srv import ResetFault
    from fluxdrive_ros import qos

    ch = new_virtual_channel()
    emu_bus = can.Bus(interface="virtual", channel=ch, fd=True)
    # the drive's over-current trip at 8 A (a stored parameter)
    emu = DriveEmulator(
        DriveSetup(short_2pct(0.1)), emu_bus, lockstep=False, params={"OVERCURRENT_A": 8.0}
    )
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain(46))
    stale_s = 0.3
    node = BenchBridgeNode(
        context=ctx,
        namespace="/bench_a",
        parameter_overrides=[
            Parameter("channel", value=ch),
            Parameter("stale_timeout_s", value=stale_s),
            Parameter("allowed_commanders", value=["*"]),
        ],
    )
    probe = rclpy.create_node("probe", context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    faults, markers, frames = [], [], []
    probe.create_subscription(DriveFault, "/bench_a/drive/fault", faults.append, qos.MARKERS)
    probe.create_subscription(
        ParameterMarker, "/bench_a/drive/param_marker", markers.append, qos.MARKERS
    )
    probe.create_subscription(PhaseFrame, "/bench_a/drive/frame", frames.append, 100)
    reset = probe.create_client(ResetFault, "/bench_a/drive/reset_fault")
    params = AsyncParameterClient(probe, "/bench_a/bench_bridge")

    def wait(cond, what: str, timeout: float = 20.0, drive: bool = False) -> None:
        t_end = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < t_end, f"no {what}: faults {faults}, markers {markers}"
            if drive:
                emu.step()  # the drive's interrupt reads its bus (ARM_MODE's reset pulse)
                time.sleep(0.01)
            else:
                time.sleep(0.02)

    try:
        spinner.start()
        assert reset.wait_for_service(timeout_sec=10.0)
        assert params.wait_for_services(timeout_sec=10.0)
        for _ in range(20):  # 20 samples, then the drive goes silent
            emu.step()
        wait(lambda: len(frames) == 20, "20 frames")
        # the supervisor's own fault: stale data
        wait(lambda: len(faults) == 1, "stale-data DriveFault")
        f = faults[0]
        assert (f.code, f.latched, f.source) == (
            DriveFault.STALE_INPUT,
            True,
            "/bench_a/bench_bridge",
        )
        assert f.reason.startswith("stale data: no valid sample for") and "latched" in f.reason
        stale = float(f.reason.split(" for ")[1].split(" s")[0])
        assert stale_s <= stale < stale_s + 5.0, f.reason
        # a parameter set through the parameter service: marked at the next sample
        fut = params.set_parameters([Parameter("stale_timeout_s", value=0.5)])
        wait(fut.done, "set_parameters answer")
        assert fut.result().results[0].successful
        wait(lambda: len(markers) == 1, "ParameterMarker")
        m = markers[0]
        assert (m.node, m.name, m.value, m.successful) == (
            "/bench_a/bench_bridge",
            "stale_timeout_s",
            "0.5",
            True,
        )
        assert m.seq == 20 and m.source == "node"
        assert node.bridge.cfg.stale_timeout_s == 0.5
        # the reset clears it: FAULT_NONE, not latched
        assert reset.call(ResetFault.Request(), timeout_sec=10.0).success
        wait(lambda: len(faults) == 2, "cleared DriveFault")
        f = faults[1]
        assert (f.code, f.latched) == (DriveFault.FAULT_NONE, False)
        assert f.reason.startswith("'stale data") and "cleared" in f.reason
        # the drive's own fault, reported in its FAULT frame: its code, "drive via" us
        # the drive's own over-current trip: phase a's sensor reads 9 A for one period
        emu.sample_hook = lambda k, fr: fr.__setitem__(FR_IA, 9.0)
        emu.step()
        emu.sample_hook = None
        assert emu.fault_latched and not emu.pwm_enabled
        emu.step()  # a sample without it: the cause is gone, a reset may clear it
        wait(lambda: len(faults) == 3, "the drive's DriveFault")
        f = faults[2]
        assert (f.code, f.latched) == (DriveFault.OVERCURRENT, True)
        assert f.source == "drive via /bench_a/bench_bridge"
        assert f.reason.startswith("drive fault 1 over-current") and "PWM off" in f.reason
        # a reset: the drive clears it and says so in a FAULT frame
        assert reset.call(ResetFault.Request(), timeout_sec=10.0).success
        wait(lambda: len(faults) == 4, "the drive's clearing", drive=True)
        f = faults[3]
        assert (f.code, f.latched, f.source) == (
            DriveFault.FAULT_NONE,
            False,
            "drive via /bench_a/bench_bridge",
        )
        assert "drive fault 1" in f.reason and "cleared" in f.reason
        assert not emu.fault_latched
    finally:
        ex.shutdown()
        spinner.join(timeout=5.0)
        node.destroy_node()
        probe.destroy_node()
        rclpy.shutdown(context=ctx)
        emu_bus.shutdown()
