"""bench_bridge node: the real drive on CAN, seen by the graph like the simulated plant.

Thin wrapper over :class:`fluxdrive.bridge.CanBridge` (all supervisor logic lives there):

* parameters: ``interface``, ``channel``, ``bitrate``, ``data_bitrate``, ``fd``,
  ``stale_timeout_s``, ``cmd_timeout_s``, ``armed`` (arm at start / live), ``frame_id``,
  ``reconnect_initial_s``, ``reconnect_max_s``, ``diagnostics_period_s``, ``ts_s``;
* publishes flux_drive_msgs/PhaseFrame on ``/drive/frame`` (header.stamp = k * ts_s,
  sample-time like the simulated plant), subscribes ``/drive/duty`` (DutyCommand) ->
  DUTY_CMD frames, service ``/drive/arm`` (flux_drive_msgs/srv/Arm) and
  ``/drive/reset_fault`` (ResetFault), diagnostics on ``/diagnostics``;
* a CAN thread polls the bus; the node disarms on shutdown.
"""

from __future__ import annotations

import sys
import threading

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from fluxdrive.bridge import (
    FRAME_FLAG_STALE_COMMAND,
    BridgeConfig,
    CanBridge,
    bus_factory_from_params,
)
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node

from flux_drive_msgs.msg import DutyCommand, PhaseFrame
from flux_drive_msgs.srv import Arm, ResetFault
from fluxdrive_ros import qos, topics

STATUS_SENSOR_CLIP = 1
STATUS_STALE_COMMAND = 16


class BenchBridgeNode(Node):
    def __init__(self, **kw) -> None:
        super().__init__("bench_bridge", **kw)
        p = self.declare_parameter
        self.p_interface = p("interface", "virtual").value
        self.p_channel = p("channel", "fluxdrive").value
        self.p_bitrate = p("bitrate", 1_000_000).value
        self.p_data_bitrate = p("data_bitrate", 5_000_000).value
        self.p_fd = p("fd", True).value
        stale = p("stale_timeout_s", 0.05).value
        cmd_to = p("cmd_timeout_s", 0.001).value
        rc0 = p("reconnect_initial_s", 0.05).value
        rc1 = p("reconnect_max_s", 2.0).value
        self.ts = p("ts_s", 1e-4).value
        self.frame_id = p("frame_id", "drive").value
        arm_at_start = p("armed", False).value
        diag_period = p("diagnostics_period_s", 1.0).value
        factory = bus_factory_from_params(self.p_interface, self.p_channel, self.p_bitrate,
                                          self.p_fd, self.p_data_bitrate)
        self.bridge = CanBridge(factory, BridgeConfig(
            stale_timeout_s=stale, cmd_timeout_s=cmd_to,
            reconnect_initial_s=rc0, reconnect_max_s=rc1))
        # the simulated plant's QoS: every reader of /drive/frame matches (volatile ones and
        # the transient-local ones of lockstep graphs); duties read like the plant reads them
        self.pub = self.create_publisher(PhaseFrame, topics.FRAME, qos.SAMPLES)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(DutyCommand, topics.DUTY, self._on_duty, qos.reader("volatile"))
        self.create_service(Arm, "/drive/arm", self._on_arm)
        self.create_service(ResetFault, "/drive/reset_fault", self._on_reset)
        self.create_timer(diag_period, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_params)
        self.bridge.connect()
        if arm_at_start:
            ok, why = self.bridge.arm()
            self.get_logger().info(f"arm at start: {ok} ({why})")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._can_loop, name="can-rx", daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- CAN side
    def _can_loop(self) -> None:
        while not self._stop.is_set():
            try:
                frames = self.bridge.poll(timeout=0.01)
            except Exception as exc:  # noqa: BLE001 - keep the supervisor alive
                self.get_logger().error(f"CAN poll: {exc!r}")
                continue
            for fr in frames:
                self.pub.publish(self._to_msg(fr))

    def _to_msg(self, fr: np.ndarray) -> PhaseFrame:
        m = PhaseFrame()
        k = int(fr[12])
        t = k * self.ts
        m.header.stamp.sec = int(t)
        m.header.stamp.nanosec = int(round((t - int(t)) * 1e9)) % 1_000_000_000
        m.header.frame_id = self.frame_id
        m.seq = max(k, 0)
        m.i_abc = [float(x) for x in fr[0:3]]
        m.v_ll = [float(x) for x in fr[3:6]]
        m.vdc = float(fr[6])
        m.duty_applied = [float(x) for x in fr[7:10]]
        m.pwm_enabled = bool(fr[10] > 0.5)
        m.encoder_counts = float(fr[11])
        fl = int(fr[13])
        m.status_flags = (STATUS_SENSOR_CLIP if fl & 1 else 0) | (
            STATUS_STALE_COMMAND if fl & FRAME_FLAG_STALE_COMMAND else 0)
        return m

    # ---------------------------------------------------------------- ROS side
    def _on_duty(self, msg: DutyCommand) -> None:
        self.bridge.send_duty(int(msg.seq), list(msg.duty), bool(msg.enable))

    def _on_arm(self, req, resp):
        ok, why = self.bridge.arm() if req.arm else self.bridge.disarm("service")
        resp.success, resp.message = bool(ok), why
        return resp

    def _on_reset(self, req, resp):
        ok, why = self.bridge.reset_fault()
        resp.success, resp.message = bool(ok), why
        return resp

    def _on_params(self, params) -> SetParametersResult:
        for prm in params:
            if prm.name == "armed":
                ok, why = self.bridge.arm() if prm.value else self.bridge.disarm("parameter")
                if not ok:
                    return SetParametersResult(successful=False, reason=why)
            elif prm.name == "stale_timeout_s":
                self.bridge.cfg.stale_timeout_s = float(prm.value)
        return SetParametersResult(successful=True)

    def _publish_diagnostics(self) -> None:
        d = self.bridge.diagnostics()
        st = DiagnosticStatus()
        st.name = "bench_bridge: CAN link"
        st.hardware_id = f"{self.p_interface}:{self.p_channel}"
        if d["state"] in ("fault", "disconnected"):
            st.level = DiagnosticStatus.ERROR
        elif d["malformed"] or d["seq_gaps"] or d["bus_errors"]:
            st.level = DiagnosticStatus.WARN
        else:
            st.level = DiagnosticStatus.OK
        st.message = d["state"] + (f": {d['fault']}" if d["fault"] else "")
        st.values = [KeyValue(key=k, value=str(v)) for k, v in d.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.diag_pub.publish(arr)

    def destroy_node(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bridge.shutdown()  # disarms first
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    rclpy.init(args=argv if argv is not None else sys.argv)
    node = BenchBridgeNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
