"""bench_bridge node: the real drive on CAN, seen by the graph like the simulated plant.

Thin wrapper over :class:`fluxdrive.can.bridge.CanBridge` (all supervisor logic lives there):

* parameters: ``interface``, ``channel``, ``bitrate``, ``data_bitrate``, ``fd``,
  ``decimation``, ``stale_timeout_s``, ``cmd_timeout_s``, ``armed`` (arm at start / live),
  ``frame_id``, ``graph_id``, ``reconnect_initial_s``, ``reconnect_max_s``,
  ``diagnostics_period_s``, ``ts_s``;
* topic and service names are relative to the drive's namespace (`__ns:=/bench_a`:
  /bench_a/drive/frame, ...; fluxdrive_ros.topics.in_drive), like the simulated plant's;
* publishes flux_drive_msgs/PhaseFrame on ``/drive/frame`` (header.stamp = k * ts_s,
  sample-time like the simulated plant; ``fd`` false selects the classic-CAN layout;
  ``decimation`` D, either layout: one sample every D PWM periods, seq = the sample index
  j, stamp = j * D * ts_s, so the observers and the controller must run at D * ts_s; the
  drive must report the same layout and D in STATUS, else arming is refused and a fault
  latched), subscribes ``/drive/duty``
  (DutyCommand) -> DUTY_CMD frames, service ``/drive/arm`` (flux_drive_msgs/srv/Arm) and
  ``/drive/reset_fault`` (ResetFault), diagnostics on ``/diagnostics``;
* split mode (``control_split``, read-only): ARM_MODE.control_split = 1, subscribes
  ``/drive/current_ref`` (CurrentReference) -> HOST_REF instead of duties;
* the drive's parameters, in both modes, are ROS parameters ``drive.<name>`` (the DBC's
  DRIVE_PARAM table, lower case: ``drive.cur_kp``, ``drive.overcurrent_a``,
  ``drive.heartbeat_timeout_s``, ...; defaults from the ``scenario``'s controller design,
  ``design_loops`` at the PWM rate, and the host heartbeat supervised), written to the
  drive as DRIVE_PARAMs and read back before every arming (arming is refused, in one line
  logged and answered, if one is refused, unanswered or read back other than written, or
  if the drive's STATUS speaks another protocol version) and whenever one is set (live:
  the set is refused with the drive's reason); the drive's FAULT frames are reported on
  /diagnostics (level ERROR, the fault named in the message);
* every fault, latched or cleared, as a flux_drive_msgs/DriveFault on ``/drive/fault``
  (reliable, transient-local, like the controller's): the drive's (its FAULT frames; source
  ``drive via <this node>``) and the supervisor's own (stale data: STALE_INPUT, a drive
  running another layout or D: BAD_SAMPLE; cleared by ``/drive/reset_fault``), stamped with
  the newest sample's time, one log line each;
* every parameter change it accepts (``armed``, ``stale_timeout_s``, ``drive.*``) as a
  ParameterMarker on ``/drive/param_marker`` (fluxdrive_ros.params.on_set), seq = the next
  sample, so the bag of a bench run holds them like a simulated run's;
* a CAN thread polls the bus; the node disarms on shutdown;
* access (fluxdrive_ros.access): duty commands are obeyed only from `allowed_commanders`
  (default /controller; others dropped and counted on /diagnostics); /drive/arm (arm) and
  /drive/reset_fault only while every node holding a client of them is in that list; a
  disarm is always obeyed.  A non-finite duty goes out as PWM off, one outside [0, 1] is
  clamped; both counted.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from fluxdrive.can.bridge import (
    BridgeConfig,
    CanBridge,
    FaultEvent,
    bus_factory_from_params,
)
from fluxdrive.can.preflight import drive_param_name
from fluxdrive.can.preflight import scenario_drive_params as drive_defaults
from fluxdrive.can.protocol import link_budget, smallest_fitting_decimation
from fluxdrive.can.realtime import HotPath
from fluxdrive.core import schema
from fluxdrive.core.schema import param
from fluxdrive.drive.control import (
    DRIVE_PARAM_RANGES,
    DriveParams,
)
from fluxdrive.drive.plant import FR_SEQ
from fluxdrive_ros.params import P, config_params, declare, on_set
from fluxdrive_ros.wire import FrameWire, Stamp
from rclpy.node import Node

from flux_drive_msgs.msg import CurrentReference, DriveFault, DutyCommand, PhaseFrame
from flux_drive_msgs.srv import Arm, ResetFault
from fluxdrive_ros import access, graph, qos, topics

_SOFTWARE_BUSES = ("virtual", "udp_multicast")  # no wire time: any layout and D "fit"
# the DRIVE_PARAM names, in the order DriveParams declares them
DRIVE_PARAMS = tuple(DRIVE_PARAM_RANGES)
# the offset calibration before arming: from the request to the drive's STATUS saying it is
# over (a drive takes 0.1 s; the virtual board, an instruction-set emulator, some seconds)
CALIBRATION_TIMEOUT_S = 60.0


def drive_param_table(values: dict[str, float]) -> list[P]:
    """Split mode: one live parameter per drive-side parameter (DriveParams; default
    `values`, the scenario's controller design)."""
    specs = schema.specs(DriveParams)
    return [
        replace(P.of(specs[prm.lower()], float(values.get(prm, 0.0))), name=drive_param_name(prm))
        for prm in DRIVE_PARAMS
    ]


# BridgeConfig fields the node declares under their own names
SUPERVISOR_FIELDS = (
    "decimation",
    "stale_timeout_s",
    "cmd_timeout_s",
    "reconnect_initial_s",
    "reconnect_max_s",
    "control_split",
)


@dataclass
class BridgeBus:
    """The CAN bus: python-can interface, channel, bit rates, FD or classic."""

    interface: str = param(
        "virtual",
        unit="",
        doc="python-can interface (virtual, socketcan, pcan, ...)",
        live=False,
    )
    channel: str = param(
        "fluxdrive",
        unit="",
        doc="python-can channel (virtual bus name, can0, ...)",
        live=False,
    )
    bitrate: int = param(
        1000000,
        unit="bit/s",
        doc="CAN (FD arbitration) bit rate",
        range=(10000, 1000000),
        live=False,
    )
    data_bitrate: int = param(
        5000000,
        unit="bit/s",
        doc="CAN FD data-phase bit rate",
        range=(125000, 12000000),
        live=False,
    )
    fd: bool = param(
        True,
        unit="",
        doc="use CAN FD frames (and the SAMPLE_FD layout; false: the classic 4-frame layout)",
        live=False,
    )


def bus_params() -> list[P]:
    """The CAN bus: python-can interface, channel, bit rates, FD or classic."""
    return config_params(BridgeBus())


def supervisor_params() -> list[P]:
    """The supervisor's settings, from the BridgeConfig schema (fluxdrive.can.bridge)."""
    specs, defaults = schema.specs(BridgeConfig), BridgeConfig()
    return [P.of(specs[name], getattr(defaults, name)) for name in SUPERVISOR_FIELDS]


@dataclass
class BridgeNodeSettings:
    """The node's own: PWM period, frame_id, arming, its diagnostics, scenario."""

    ts_s: float = param(
        1e-4,
        unit="s",
        doc="PWM period of the drive (header.stamp = seq * ts_s)",
        range=(1e-6, 1e-2),
        live=False,
    )
    frame_id: str = param(
        "drive",
        unit="",
        doc="header.frame_id of published frames",
        live=False,
    )
    armed: bool = param(
        False,
        unit="",
        doc="arm the drive (at start, and live: true arms, false disarms; refused"
        " with the reason while a fault is latched)",
    )
    arm_wait_s: float = param(
        0.0,
        unit="s",
        doc="with armed at start: keep trying to arm this long, for a drive that "
        "comes up on the bus after this node (0: one attempt)",
        range=(0.0, 600.0),
        live=False,
    )
    calibrate_before_arming: bool = param(
        True,
        unit="",
        doc="before the first arming after (re)connecting, the drive's current and capture "
        "offset calibration (ARM_MODE mode CALIBRATE_ADC: the motor at standstill, PWM off); "
        "false: arm a drive calibrated otherwise (bench --calibrate)",
        live=False,
    )
    diagnostics_period_s: float = param(
        1.0,
        unit="s",
        doc="period of the /diagnostics status",
        range=(0.05, 60.0),
        live=False,
    )
    scenario: str = param(
        "",
        unit="",
        doc="scenario YAML (path or name) whose controller design gives the "
        "drive.* defaults (split mode; empty: the default machine card's)",
        live=False,
    )
    realtime_priority: int = param(
        0,
        unit="",
        doc="SCHED_FIFO priority of the CAN thread, the hot path from a sample to its "
        "answer, with the process's memory locked and the garbage collector off that "
        "path (fluxdrive.can.realtime; not permitted: one warning line; 0: normal "
        "scheduling)",
        range=(0, 99),
        live=False,
    )
    realtime_cpu: int = param(
        -1,
        unit="",
        doc="core the CAN thread is pinned to (an isolated one on a bench PC; -1: any)",
        range=(-1, 1023),
        live=False,
    )


def node_params() -> list[P]:
    """The node's own: PWM period, frame_id, arming, diagnostics, scenario, access, graph."""
    return [*config_params(BridgeNodeSettings()), access.param(), graph.param()]


def param_table() -> list[P]:
    """The bridge's declared parameters (description, unit, range; live ones marked)."""
    return bus_params() + supervisor_params() + node_params()


class BenchBridgeNode(Node):
    def __init__(self, **kw) -> None:
        super().__init__("bench_bridge", **kw)
        pv = declare(self, param_table())
        self.p_interface = pv["interface"]
        self.p_channel = pv["channel"]
        self.p_bitrate = pv["bitrate"]
        self.p_data_bitrate = pv["data_bitrate"]
        self.p_fd = pv["fd"]
        self.p_decimation = int(pv["decimation"])
        self.ts = pv["ts_s"]
        self.frame_id = pv["frame_id"]
        self.split = bool(pv["control_split"])
        self.p_calibrate = bool(pv["calibrate_before_arming"])
        # the drive's parameters, both modes (host mode: its protections and supervision)
        self.drive_specs = drive_param_table(drive_defaults(pv["scenario"]))
        self.drive_values = declare(self, self.drive_specs)
        # the allow-list names nodes of this drive (/controller: <namespace>/controller)
        self.allowed = topics.drive_names(self, list(pv["allowed_commanders"]))
        # graph identity (fluxdrive_ros.graph): its frames carry the graph's id, duties of
        # another graph are dropped and counted
        self.graph = graph.Membership(self, pv["graph_id"])
        self.guard = access.CommandGuard(
            self.allowed, topics.CURRENT_REF if self.split else topics.DUTY
        )
        self.duty_out_of_range = 0
        self.service_refused = 0
        self.bridge = self._make_bridge(pv)
        self.bridge.require_params = True  # arming: written and read back first
        self._report_link()
        self._mismatch_logged = ""
        self._wire(pv["diagnostics_period_s"])
        # every accepted change is a marker in the bag, at the next sample
        on_set(
            self,
            param_table() + self.drive_specs,
            self._apply_params,
            sample=lambda: self.bridge.newest_sample + 1,
            ts_s=self.ts * self.bridge.decimation,
        )
        self.bridge.connect()
        self._stop = threading.Event()
        cpu = int(pv["realtime_cpu"])
        self._hot = HotPath(int(pv["realtime_priority"]), None if cpu < 0 else cpu)
        self._thread = threading.Thread(target=self._can_loop, name="can-rx", daemon=True)
        self._thread.start()
        if pv["armed"]:
            self._arm_at_start(float(pv["arm_wait_s"]))

    def _make_bridge(self, pv: dict) -> CanBridge:
        """The engine's supervisor on the configured bus, with the declared settings."""
        factory = bus_factory_from_params(
            self.p_interface, self.p_channel, self.p_bitrate, self.p_fd, self.p_data_bitrate
        )
        return CanBridge(
            factory,
            BridgeConfig(**{name: pv[name] for name in SUPERVISOR_FIELDS}),
        )

    def _wire(self, diag_period: float) -> None:
        """Frames out, duties or references in, the arm and reset services, diagnostics."""
        # the simulated plant's QoS: every reader of /drive/frame matches (volatile ones and
        # the transient-local ones of lockstep graphs); duties read like the plant reads them
        self.pub = self.create_publisher(
            PhaseFrame, topics.drive_topic(self, topics.FRAME), qos.SAMPLES
        )
        self.wire = FrameWire(self.frame_id, graph_id=self.graph.id)
        self._stamp_d = 0
        self._stamp = Stamp(self.ts)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.fault_pub = self.create_publisher(
            DriveFault, topics.drive_topic(self, topics.FAULT), qos.MARKERS
        )
        if self.split:
            self.create_subscription(
                CurrentReference,
                topics.drive_topic(self, topics.CURRENT_REF),
                self.graph.typed(topics.CURRENT_REF, self._on_reference),
                qos.reader("volatile"),
            )
        else:
            self.create_subscription(
                DutyCommand,
                topics.drive_topic(self, topics.DUTY),
                self.graph.typed(topics.DUTY, self._on_duty),
                qos.reader("volatile"),
            )
        self.arm_service = topics.in_drive(self, "drive/arm")
        self.reset_service = topics.in_drive(self, "drive/reset_fault")
        self.create_service(Arm, self.arm_service, self._on_arm)
        self.create_service(ResetFault, self.reset_service, self._on_reset)
        self.create_timer(diag_period, self._publish_diagnostics)

    def _arm_at_start(self, wait_s: float) -> None:
        """Arm now; for a drive that comes up later, retry for `wait_s` (0: once)."""
        deadline = time.monotonic() + wait_s
        ok, why = self._arm()
        while not ok and time.monotonic() < deadline:
            time.sleep(0.2)
            ok, why = self._arm()
        self.get_logger().info(f"arm at start: {ok} ({why})")

    def _report_link(self) -> None:
        """Log the layout and D; warn when they do not fit the configured bus."""
        br = self.bridge
        self.get_logger().info(
            f"{br.layout} layout, D={br.decimation}: a sample every "
            f"{br.decimation * self.ts * 1e3:g} ms (observers and controller must run at "
            f"ts = {br.decimation * self.ts:g} s)"
        )
        if self.p_interface in _SOFTWARE_BUSES:
            return
        kw = {
            "pwm_hz": 1.0 / self.ts,
            "nominal_bitrate": float(self.p_bitrate),
            "data_bitrate": float(self.p_data_bitrate),
        }
        lb = link_budget(br.layout, decimation=br.decimation, **kw)
        if not lb["fits"]:
            try:
                need = f"decimation >= {smallest_fitting_decimation(br.layout, **kw)}"
            except ValueError:
                need = "a faster bus"
            self.get_logger().warning(
                f"the {br.layout} layout at D={br.decimation} needs "
                f"{100 * lb['load_none']:.0f}-{100 * lb['load_worst']:.0f} % of this "
                f"{self.p_bitrate / 1e6:g}/{self.p_data_bitrate / 1e6:g} Mbit/s bus (host "
                f"budget {lb['host_budget_us_worst']:.0f} us per sample): use {need}"
            )

    # ---------------------------------------------------------------- CAN side
    def _can_loop(self) -> None:
        """The hot path (fluxdrive.can.realtime.HotPath: real time as far as permitted,
        said in the log): poll, publish each sample, faults."""
        with self._hot as hot:
            if hot.priority > 0:
                self.get_logger().info(hot.report.line())
                for note in hot.report.notes:
                    self.get_logger().warning(note)
            while not self._stop.is_set():
                try:
                    frames = self.bridge.poll(timeout=0.01)
                except Exception as exc:  # noqa: BLE001 - keep the supervisor alive
                    self.get_logger().error(f"CAN poll: {exc!r}")
                    continue
                try:
                    for fr in frames:
                        self.pub.publish(self._to_msg(fr))
                    while self.bridge.fault_events:
                        self._publish_fault(self.bridge.fault_events.popleft())
                except Exception:  # noqa: BLE001 - rclpy shut down under us: the run is over
                    if self.context.ok():
                        raise
                    return
                hot.after_answer()  # a young collection when one is due

    def _publish_fault(self, ev: FaultEvent) -> None:
        """A fault latched or cleared on the bench as a DriveFault, stamped with the newest
        sample's time, and one log line."""
        m = DriveFault()
        j = self.bridge.newest_sample
        m.header.stamp.sec, m.header.stamp.nanosec = self._stamp(j)
        m.header.frame_id = self.frame_id
        m.code, m.latched, m.reason = int(ev.code), bool(ev.latched), ev.reason
        fqn = self.get_fully_qualified_name()
        m.source = fqn if ev.origin == "host" else f"drive via {fqn}"
        self.fault_pub.publish(m)
        text = f"fault {ev.code} ({m.source}) at sample {j}: {ev.reason}"
        if ev.latched:
            self.get_logger().error(text)
        else:
            self.get_logger().info(text)

    def _to_msg(self, fr: np.ndarray) -> bytes:
        """A decoded sample -> PhaseFrame bytes (the one mapping, fluxdrive.io.messages);
        seq = the sample index j, one every D periods, stamped j * D * Ts."""
        k = max(int(fr[FR_SEQ]), 0)
        fr[FR_SEQ] = k
        if self._stamp_d != self.bridge.decimation:
            self._stamp_d = self.bridge.decimation
            self._stamp = Stamp(self.ts * self._stamp_d)
        return self.wire.pack(fr, *self._stamp(k))

    # ---------------------------------------------------------------- ROS side
    def _on_duty(self, msg: DutyCommand) -> None:
        if not self.guard.accept_mark(msg.commander):
            if self.guard.n_rejected <= 3:
                self.get_logger().warning(
                    f"duty command dropped ({self.guard.last_rejected}); "
                    f"obeyed only from {self.allowed}"
                )
            return
        d = list(msg.duty)
        if all(math.isfinite(x) for x in d) and not all(-1e-9 <= x <= 1.0 + 1e-9 for x in d):
            self.duty_out_of_range += 1  # clamped by send_duty; non-finite counted there
        self.bridge.send_duty(int(msg.seq), d, bool(msg.enable))

    def _on_reference(self, msg: CurrentReference) -> None:
        if not self.guard.accept_mark(msg.commander):
            if self.guard.n_rejected <= 3:
                self.get_logger().warning(
                    f"current reference dropped ({self.guard.last_rejected}); "
                    f"obeyed only from {self.allowed}"
                )
            return
        self.bridge.send_reference(
            int(msg.seq), msg.id_ref, msg.iq_ref, msg.theta_e, msg.omega_e, bool(msg.enable)
        )

    def _push_drive_params(self, values: dict[str, float]) -> str:
        """Write drive parameters (DRIVE_PARAM name -> value) and read them back; '' or
        the first refusal or mismatch."""
        ok, why = self.bridge.write_drive_params({p: float(v) for p, v in values.items()})
        return "" if ok else why

    def _arm(self) -> tuple[bool, str]:
        """Arm, both modes: the drive first gets every drive.* value, acknowledged and read
        back; a refusal, a mismatch or another protocol version refuses, said in one line."""
        vals = {prm: self.drive_values[drive_param_name(prm)] for prm in DRIVE_PARAMS}
        why = self.bridge.arm_refusal() or self._push_drive_params(vals) or self._calibrate()
        if why:
            self.get_logger().error(f"not armed: {why}")
            return False, why
        ok, why = self.bridge.arm()
        if not ok:
            self.get_logger().error(f"not armed: {why}")
        return ok, why

    def _calibrate(self) -> str:
        """The offset calibration before the first arming since the bus (re)connected
        (calibrate_before_arming); '' or why it failed."""
        br = self.bridge
        if not self.p_calibrate or br.calibrated or br.armed:
            return ""
        ok, why = br.calibrate(CALIBRATION_TIMEOUT_S, CALIBRATION_TIMEOUT_S)
        if not ok:
            return f"offset calibration: {why}"
        self.get_logger().info(f"before arming: {why}")
        return ""

    def _refused(self, service: str) -> str | None:
        why = access.check_service_caller(self, service, self.allowed)
        if why:
            self.service_refused += 1
            self.get_logger().warning(why)
        return why

    def _on_arm(self, req, resp):
        why = self._refused(self.arm_service) if req.arm else None  # disarm: always obeyed
        if why:
            resp.success, resp.message = False, why
            return resp
        ok, why = self._arm() if req.arm else self.bridge.disarm("service")
        resp.success, resp.message = bool(ok), why
        return resp

    def _on_reset(self, req, resp):
        why = self._refused(self.reset_service)
        if why:
            resp.success, resp.message = False, why
            return resp
        ok, why = self.bridge.reset_fault()
        resp.success, resp.message = bool(ok), why
        return resp

    def _apply_params(self, changes: dict) -> str | None:
        drive = {
            p: changes[drive_param_name(p)] for p in DRIVE_PARAMS if drive_param_name(p) in changes
        }
        if drive:  # the drive must acknowledge, else the set is refused with its reason
            why = self._push_drive_params(drive)
            if why:
                raise ValueError(why)
            self.drive_values.update({drive_param_name(p): v for p, v in drive.items()})
        if "armed" in changes:
            ok, why = self._arm() if changes["armed"] else self.bridge.disarm("parameter")
            if not ok:
                raise ValueError(why)
        if "stale_timeout_s" in changes:
            self.bridge.cfg.stale_timeout_s = float(changes["stale_timeout_s"])
        return None

    def _publish_diagnostics(self) -> None:
        d = self.bridge.diagnostics()
        st = DiagnosticStatus()
        st.name = "bench_bridge: CAN link"
        st.hardware_id = f"{self.p_interface}:{self.p_channel}"
        mismatch = d["drive_mismatch"]
        if mismatch and mismatch != self._mismatch_logged:
            self.get_logger().error(
                f"{mismatch}: arming refused (set the decimation and "
                f"fd parameters to what the drive runs, or reflash it)"
            )
        self._mismatch_logged = mismatch
        if d["state"] in ("fault", "disconnected") or d["drive_fault"]:
            st.level = DiagnosticStatus.ERROR
        elif (
            d["malformed"]
            or d["seq_gaps"]
            or d["seq_rejected"]
            or d["bus_errors"]
            or self.guard.n_rejected
            or d["layout_mismatch"]
            or self.duty_out_of_range
            or d.get("duty_nonfinite")
            or self.service_refused
        ):
            st.level = DiagnosticStatus.WARN
        else:
            st.level = DiagnosticStatus.OK
        st.message = d["state"] + (f": {d['fault']}" if d["fault"] else "")
        if d["drive_fault"]:  # logged once, with its DriveFault (_publish_fault)
            st.message += f"; {d['drive_fault']}"
        d.update(
            self.guard.values(),
            duty_out_of_range=self.duty_out_of_range,
            service_requests_refused=self.service_refused,
        )
        st.values = [KeyValue(key=k, value=str(v)) for k, v in d.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.diag_pub.publish(arr)

    def link_summary(self) -> str:
        """One line at the end: the samples handed on and what was dropped, by kind."""
        d = self.bridge.diagnostics()
        return (
            f"CAN link: {d['frames_out']} samples handed on; dropped: {d['seq_duplicates']} "
            f"duplicates, {d['seq_out_of_order']} out of order, {d['seq_jumps']} jumps, "
            f"{d['malformed']} malformed; {d['seq_gaps']} gaps ({d['seq_lost']} lost); "
            f"{d.get('rx_other', 0)} frames of other IDs"
        )

    def destroy_node(self) -> None:
        if self.graph.foreign:
            self.get_logger().warning(self.graph.summary())
        self._stop.set()
        self._thread.join(1.0)
        self.get_logger().info(self.link_summary())
        self.bridge.shutdown()  # disarms first
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    rclpy.init(args=argv if argv is not None else sys.argv)
    node = BenchBridgeNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    except RuntimeError:
        if rclpy.ok():
            raise
        # a SIGINT/SIGTERM shut the context down while the executor was taking a message:
        # rclpy reports the invalidated handle as a RuntimeError ("Unable to convert call
        # argument"); it is the stop that was asked for (the drive is disarmed below)
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
