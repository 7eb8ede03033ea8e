"""foc_controller_node: field-oriented control as a ROS node.

A thin wrapper around fluxdrive.drive.control.controller_step.  For every sample k it waits for
PhaseFrame k and, when sensorless (position_source = estimate), the RotorEstimate k of the
driving observer (`estimate_topic`), then computes duty(k) and publishes DutyCommand(seq=k)
on /drive/duty and ControllerState(seq=k) on /drive/controller_state.  Samples are
processed strictly in order, so the graph reproduces the in-process runner exactly.

Parameters: every field of fluxdrive.drive.control.ControllerConfig (gains derive from the
bandwidths), declared with description, unit and range; all but position_source and
estimate_topic are live: a change re-runs the gain design (ControllerConfig.to_params) and
replaces the kernel's parameter row from the next sample.  A change the design refuses
(e.g. a current bandwidth the 1.5-period delay cannot reach, handback >= handover) is
rejected with the reason.  The speed reference follows the scenario's profile (with its
injection) unless speed_ref_mode = constant (speed_ref_rpm).

Split mode (`control_mode` = split, read-only; default the scenario's control.mode): the
drive closes the current loop; this node runs `host_reference_step` (everything but the
current loops) and publishes CurrentReference(seq=k) on /drive/current_ref instead of
duties.  `decimation` (read-only): the frames come every D-th PWM period, the node steps at
D * the card's Ts (split: the drive's current gains stay the PWM-rate design; host mode: the
loops are designed for the sample rate).

The sequencing -- frame/estimate pairing, stale-input trips, the drive picking up after the
power stage's watchdog switched the PWM off, one log line per latched fault -- is the
engine's fluxdrive.drive.sequencer.ControlSequencer; this node feeds it and publishes.

Bad input and a lost position source (safe state = DutyCommand enable = false, latched
fault in ControllerState.fault_code, its name in fault_reason, until an explicit reset: the
~/reset_fault service
(flux_drive_msgs/ResetFault, e.g. `./fluxdrive fault reset`), obeyed only while every
client of it is in `allowed_operators`; the drive then starts again from align / I-f):
- the engine trips at once on a non-finite frame (bad sample), over-current, DC-bus over-
  or under-voltage, over-speed, a non-finite estimate, and -- in closed loop -- on an
  estimate flagged invalid for longer than `invalid_timeout_s` (loss of lock);
- here: when the driving estimate of a received frame does not come -- frames
  `position_timeout_s` of sample time later are already here (bench, paced plant; once a
  first estimate has come), or it
  has been waited for `position_wall_timeout_s` of wall time (lockstep: the plant waits for
  us, so sample time stands still; 30 s for the very first estimate) -- the controller
  trips with "stale input" and from then on answers every frame at once with the PWM off;
- a frame whose seq repeats or goes backwards is dropped; a jump skips the missing
  samples (frames lost upstream: never waited for); `position_timeout_s` worth of
  consecutive dropped frames (e.g. a restarted source counting from 0 again) trips
  "stale input" too.  Everything is counted on /diagnostics ("<node>: input", "<node>:
  state").
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass

import numpy as np
from fluxdrive.core import schema
from fluxdrive.core.machine import load_machine
from fluxdrive.core.schema import param
from fluxdrive.drive.control import (
    CO_EN,
    CO_FAULT,
    CO_MODE,
    CO_N,
    CS_FAULT,
    FAULT_NAMES,
    MODE_NAMES,
    ControllerConfig,
    host_params,
)
from fluxdrive.drive.observers import ES_N
from fluxdrive.drive.plant import FR_N
from fluxdrive.drive.scenario import CONFIG_DIR, RPM, load_scenario, scenario_path
from fluxdrive.drive.sequencer import ControlSequencer
from fluxdrive.drive.sim import DriveSetup
from fluxdrive.io.messages import ReferenceWire
from fluxdrive_ros.intra import BlockSender, RawPublisher, RawSubscription
from fluxdrive_ros.params import P, declare, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from fluxdrive_ros.wire import ControlWire, EstimateWire, FrameWire, Stamp

import flux_drive_msgs.msg as fm
from flux_drive_msgs.srv import ResetFault
from fluxdrive_ros import access, params, qos, topics
from fluxdrive_ros import diagnostics as diag

# ControllerConfig fields declared on their own (read-only, under the node's names) or not
# at all (host_delay_samples: an in-process timing knob), not among the live parameters
FIXED_FIELDS = ("position_source", "mode", "decimation", "host_delay_samples")
# the live parameters that are ControllerConfig fields (the rest are the node's own)
CONFIG_FIELDS = frozenset(schema.specs(ControllerConfig))
# wall-clock grace for the very first estimate (a starting observer process, compilation)
FIRST_ESTIMATE_WALL_S = 30.0


@dataclass
class ControllerInput:
    """Where the node's defaults come from."""

    scenario: str = param(
        "",
        unit="",
        doc="scenario YAML (path or a name under config/scenarios): machine card,"
        " controller defaults, speed profile and injections",
        live=False,
    )
    machine: str = param(
        str(CONFIG_DIR / "machines" / "default_spm.yaml"),
        unit="",
        doc="machine card YAML when no scenario is given",
        live=False,
    )


def input_params() -> list[P]:
    """Where the node's defaults come from: a scenario, else a machine card."""
    return params.config_params(ControllerInput())


@dataclass
class ControllerTopic:
    """Where the driving estimate comes from."""

    estimate_topic: str = param(
        "",
        unit="",
        doc="RotorEstimate topic of the driving observer (position_source = "
        "estimate; relative: in the drive's namespace)",
        live=False,
    )


def source_params(cfg: ControllerConfig, driving: str) -> list[P]:
    """The read-only choices of a run: position source, its topic, where the current loop
    runs and the decimation (from the ControllerConfig schema, under the node's names)."""
    spec = schema.specs(ControllerConfig)
    mode = dataclasses.replace(P.of(spec["mode"], cfg.mode), name="control_mode")
    topic = topics.estimate_topic(driving if driving != "encoder" else "flux_measured")
    return [
        P.of(spec["position_source"], cfg.position_source),
        *params.config_params(ControllerTopic(topics.rel(topic))),
        mode,
        P.of(spec["decimation"], int(cfg.decimation)),
    ]


@dataclass
class ControllerNodeSettings:
    """The node's own live and read-only parameters."""

    speed_ref_mode: str = param(
        "profile",
        unit="",
        doc="speed reference: the scenario's profile or the constant speed_ref_rpm",
        choices=("profile", "constant"),
    )
    speed_ref_rpm: float = param(
        0.0,
        unit="rpm",
        doc="constant mechanical speed reference",
        range=(-1e5, 1e5),
    )
    position_timeout_s: float = param(
        0.05,
        unit="s",
        doc="safe state (PWM off, latched 'stale input') when the driving "
        "estimate of a frame has not come while frames this much sample time "
        "later have",
        range=(1e-4, 10.0),
    )
    position_wall_timeout_s: float = param(
        2.0,
        unit="s",
        doc="safe state when the driving estimate of a waiting frame has not come"
        " for this much wall time (lockstep graphs, where the plant waits for"
        " us; 0: off)",
        range=(0.0, 3600.0),
    )
    max_resyncs: int = param(
        5,
        unit="-",
        doc="lost intervals (PWM switched off by the power stage's watchdog) "
        "tolerated within resync_window_s; one more latches the fault "
        "'watchdog'.  A drive on a bus and a lockstep plant also switch it "
        "off for a late host, a lost frame or a restarted controller's first "
        "answers; with the paced plant, which takes only a silent controller "
        "for dead, 0 latches the first",
        range=(0, 1000),
        live=False,
    )
    resync_window_s: float = param(
        10.0,
        unit="s",
        doc="sample-time window of max_resyncs",
        range=(0.01, 3600.0),
        live=False,
    )


def node_params() -> list[P]:
    """The node's own live and read-only parameters (speed reference, timeouts, resyncs)."""
    return params.config_params(ControllerNodeSettings())


@dataclass
class ControllerCommon:
    """The frame_id of what it publishes, who may reset a fault."""

    frame_id: str = param(
        "",
        unit="",
        doc="header.frame_id of ControllerState and DutyCommand (the access mark "
        "travels in DutyCommand.commander)",
        live=False,
    )
    allowed_operators: tuple[str, ...] = param(
        access.DEFAULT_OPERATORS,
        unit="",
        doc="nodes (fully qualified names) whose ~/reset_fault requests are obeyed; '*' = anyone",
        live=False,
    )


def common_params() -> list[P]:
    """Input topic and durability, frame_id, diagnostics, who may reset a fault."""
    common = params.config_params(ControllerCommon())
    return [*params.frame_input_params(), common[0], diag.PARAM, common[1]]


def design_card(card, split: bool, decimation: int):
    """(card, decimation) the node's settings are checked on: split, the drive's card at the
    decimation; host mode at D > 1, the loops designed for the sample rate (PWM / D)."""
    if decimation > 1 and not split:
        return dataclasses.replace(card, pwm_hz=card.pwm_hz / decimation), 1
    return card, decimation


class ControllerNode(FluxNode):
    w_ref_profile: np.ndarray  # the speed reference per sample [rad/s mechanical]
    id_inj: np.ndarray  # the d-current injection per sample [A]

    def __init__(self, name: str = "controller", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        card, cfg, driving = self._load(declare(self, input_params()))
        src = declare(self, source_params(cfg, driving))
        self.split = src["control_mode"] == "split"
        self.decimation = int(src["decimation"])
        d = self.decimation
        self.w_ref_profile, self.id_inj = self.w_ref_profile[::d], self.id_inj[::d]
        # every card-derived default (bus window, bandwidths, handover) as a concrete value:
        # ROS parameters cannot say "derive it"
        cfg = dataclasses.replace(cfg, position_source=src["position_source"]).resolved(card)
        self.card = card
        live = params.config_params(cfg, *design_card(card, self.split, d), skip=FIXED_FIELDS)
        self.specs = live + node_params()
        pv = declare(self, self.specs)
        common = declare(self, common_params())
        self.allowed_operators = list(common["allowed_operators"])
        self.pv = pv
        self.cfg = params.to_config(cfg, pv)
        self.cp = self._params(self.cfg)
        self.sensorless = self.cfg.position_source == "estimate"
        self._wire(card, pv, common, src["estimate_topic"])
        on_set(self, self.specs, self._apply, lambda: self.seq.next_k, card.ts_s)
        self.diag = diag.Diagnostics(self, common["diagnostics_period_s"])
        self.diag.add("input", self._diag_input)
        self.diag.add("state", self._diag_state)
        # the estimate's wall-clock timeout, and frames that stop coming (either source)
        self.create_timer(0.1, self._check_wall_timeout)
        self.get_logger().info(
            "position from "
            + (src["estimate_topic"] if self.sensorless else "the encoder")
            + f"; current loop {self.cfg.current_bandwidth_hz:g} Hz, speed loop "
            f"{self.cfg.speed_bandwidth_hz:g} Hz"
        )

    def _load(self, first: dict):
        """(card, ControllerConfig, driving observer) of the scenario or the machine card;
        sets the speed profile and the d-current injection."""
        if first["scenario"]:
            sc = load_scenario(scenario_path(first["scenario"]))
            ds = DriveSetup(sc)
            self.w_ref_profile, self.id_inj = ds.w_ref, ds.id_inj
            return sc.machine, sc.control, sc.driving
        self.w_ref_profile, self.id_inj = np.zeros(1), np.zeros(1)
        return load_machine(first["machine"]), ControllerConfig(), "encoder"

    def _sequencer(self, card, pv: dict) -> ControlSequencer:
        """The engine's sequencer: pairing, stale-input trips, lost-interval resyncs."""
        return ControlSequencer(
            self.cp,
            card.ts_s * self.decimation,
            self.sensorless,
            self._publish,
            self._log,
            self.w_ref_profile,
            self.id_inj,
            pv["position_timeout_s"],
            pv["position_wall_timeout_s"],
            FIRST_ESTIMATE_WALL_S,
            qos.SAMPLE_DEPTH,
            pv["max_resyncs"],
            pv["resync_window_s"],
            split=self.split,
            own_rows=True,  # _on_frame / _on_est: rows of their own, float64
        )

    def _wire(self, card, pv: dict, common: dict, estimate_topic: str) -> None:
        """Wire formats, the sequencer, publishers, subscriptions, fault events, reset."""
        self.stamp = Stamp(card.ts_s * self.decimation)
        self.fw = FrameWire()
        self.ew = EstimateWire("")
        # DutyCommand.commander = this node's mark: the plant / bench bridge obey
        # only marked commands of their allowed_commanders (fluxdrive_ros.access)
        self.cw = ControlWire(
            common["frame_id"],
            commander=access.mark(self.get_fully_qualified_name(), topics.DUTY),
            graph_id=self.graph.id,
        )
        self.rw = ReferenceWire(
            common["frame_id"],
            commander=access.mark(self.get_fully_qualified_name(), topics.CURRENT_REF),
            graph_id=self.graph.id,
        )
        # pairing, stale-input trips, lost-interval re-synchronisation: the engine's
        self.seq = self._sequencer(card, pv)
        self.counts = diag.Counters(*self.seq.counts)
        self.counts.values = self.seq.counts
        self.done_seq: int | None = None
        self.exit_on_done = common["exit_on_done"]
        self._set_ref(pv)
        in_drive = topics.drive_topic
        if self.split:
            self.pub_duty = RawPublisher(
                self,
                fm.CurrentReference,
                in_drive(self, topics.CURRENT_REF),
                qos.SAMPLES,
                stamp=self.stamp,
            )
        else:
            self.pub_duty = RawPublisher(
                self, fm.DutyCommand, in_drive(self, topics.DUTY), qos.SAMPLES, stamp=self.stamp
            )
        self.pub_state = RawPublisher(
            self, fm.ControllerState, in_drive(self, topics.CONTROLLER_STATE), qos.SAMPLES
        )
        # the state feeds nothing back: published in blocks (at most 0.1 s late, the timer)
        self.state_blocks = BlockSender(self.pub_state, self.stamp)
        self.sub_frame = RawSubscription(
            self,
            fm.PhaseFrame,
            topics.in_drive(self, common["frame_topic"]),
            self._on_frame,
            qos.reader(common["input_durability"]),
            row_callback=self._on_frame_row,
        )
        self.sub_est = None
        if self.sensorless:
            self.sub_est = RawSubscription(
                self,
                fm.RotorEstimate,
                topics.in_drive(self, estimate_topic),
                self._on_est,
                qos.reader(common["input_durability"]),
                row_callback=self._on_est_row,
            )
        self.create_subscription(
            fm.RunDone,
            in_drive(self, topics.DONE),
            self.graph.typed(topics.DONE, self._on_done),
            qos.LATCHED,
        )
        # every fault latched, and its reset, as a DriveFault event (reliable, transient-
        # local: a late reader, the recorder, still gets it)
        self.pub_fault = self.create_publisher(
            fm.DriveFault, in_drive(self, topics.FAULT), qos.MARKERS
        )
        self._fault_code = 0.0  # CO_FAULT of the last published sample
        self.state_rc = self.cw.state_codec(np.zeros(CO_N))  # the ControllerState codec of it
        self.es = np.empty(ES_N)  # each estimate's row
        self.reset_service = self.resolve_service_name("~/reset_fault")
        self.create_service(ResetFault, self.reset_service, self._on_reset)

    # ----------------------------------------------------------------- parameters
    def _params(self, cfg: ControllerConfig) -> np.ndarray:
        """The kernel's row at this node's sample time: split, the host's half of the
        PWM-rate design; host mode at D > 1, the loops designed for the sample rate."""
        d = self.decimation
        card, _ = design_card(self.card, self.split, d)  # what the descriptors' ranges say
        if self.split:
            split = dataclasses.replace(cfg, mode="split", decimation=d)
            return host_params(split.to_params(card), d)
        return dataclasses.replace(cfg, mode="host", decimation=1).to_params(card)

    def _set_ref(self, pv) -> None:
        self.seq.set_timeouts(pv["position_timeout_s"], pv["position_wall_timeout_s"])
        self.seq.const_ref = (
            pv["speed_ref_rpm"] * RPM if pv["speed_ref_mode"] == "constant" else None
        )

    def _apply(self, changes: dict) -> str:
        new = {**self.pv, **changes}
        ctrl = {k: v for k, v in changes.items() if k in CONFIG_FIELDS}
        if ctrl:
            cfg = params.to_config(self.cfg, ctrl)
            cp = self._params(cfg)  # ConfigError (a ValueError) -> rejected
            self.cp[:] = cp
            self.cfg = cfg
        self.pv = new
        self._set_ref(new)
        return f"applied from sample {self.seq.next_k}"

    # ----------------------------------------------------------------- samples
    def _on_frame(self, data: bytes) -> None:
        # the sequencer keeps the frame until it is answered, then hands its row back
        spare = self.seq.spare
        fr = spare.pop() if spare else np.empty(FR_N)
        self.seq.on_frame(self.fw.unpack(data, fr), fr)

    def _on_frame_row(self, msg: tuple) -> None:
        """A frame of the plant in this process, as its row (fluxdrive_ros.intra): a new
        row, which nobody writes -- kept as it is until answered."""
        self.seq.on_frame(msg[1], msg[0])

    def _on_est(self, data: bytes) -> None:
        es = self.es  # the sequencer keeps a copy if it keeps the estimate
        self.seq.on_estimate(self.ew.unpack(data, es), es)

    def _on_est_row(self, msg: tuple) -> None:
        """The driving observer's estimate in this process, as its row."""
        self.seq.on_estimate(msg[1], msg[0])

    def _publish(self, k: int, out: np.ndarray) -> None:
        if self.split:
            self.pub_duty.publish_row(self.rw.rc, self.seq.ref, k)
        else:
            self.pub_duty.publish_row(self.cw.duty, out, k)
        fault = out.item(CO_FAULT)
        # the state's codec goes with its fault text (ControlWire.state_codec)
        rc = self.state_rc if fault == self._fault_code else self.cw.state_codec(out)
        self.state_blocks.add(rc, out, k)
        if fault != self._fault_code:  # latched or cleared at this sample
            self._fault_event(k, out, *self.stamp(k))
        if self.done_seq is not None and k >= self.done_seq:
            self.state_blocks.flush()
            self.finished = True

    def _fault_event(self, k: int, out: np.ndarray, sec: int, nsec: int) -> None:
        """A DriveFault on drive/fault: the code latched at sample k (PWM off), or
        FAULT_NONE once a reset cleared it."""
        code = int(out[CO_FAULT])
        before = int(self._fault_code)
        self._fault_code = out.item(CO_FAULT)
        self.state_rc = self.cw.state_codec(out)
        m = fm.DriveFault()
        m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
        m.header.frame_id = self.cw.frame_id
        m.code = code
        m.source = self.get_fully_qualified_name()
        m.latched = code != 0
        if code:
            m.reason = f"{FAULT_NAMES.get(code, str(code))} at sample {k}: PWM off, latched"
        else:
            m.reason = f"'{FAULT_NAMES.get(before, str(before))}' cleared; running from sample {k}"
        self.pub_fault.publish(m)

    def _log(self, level: str, text: str) -> None:
        self.log(text, level)  # the sequencer's (level, text) onto FluxNode.log

    def _check_wall_timeout(self) -> None:
        self.state_blocks.flush()
        if not self.finished:  # past the run's last sample no frame is due
            self.seq.check_wall()

    def _on_reset(self, req, resp):  # noqa: ARG002 - the request is empty
        """Explicit reset of a latched fault (the only way one is cleared)."""
        why = access.check_service_caller(
            self, self.reset_service, self.allowed_operators, "allowed_operators"
        )
        if why:
            self.get_logger().warning(f"reset_fault {why}")
            resp.success, resp.message = False, why
            return resp
        if not self.seq.tripped:
            resp.success, resp.message = True, "no latched fault"
            return resp
        code, detail = self.seq.reset_fault()
        name = FAULT_NAMES.get(code, str(code))
        detail = f" ({detail})" if detail else ""
        msg = (
            f"cleared latched fault '{name}'{detail}; from sample {self.seq.next_k} the drive "
            f"starts again (align, I-f, handover)"
        )
        self.get_logger().warning(msg)
        resp.success, resp.message = True, msg
        return resp

    # ----------------------------------------------------------------- diagnostics
    def _diag_input(self) -> tuple[int, str, dict]:
        c, sq = self.counts, self.seq
        grew = c.grew("repeated_or_backwards", "missing_frames", "late_estimates", "lost_frames")
        values = {
            **c.report(),
            "next_sample": sq.next_k,
            "last_frame_seq": sq.max_seq,
            "pending_frames": len(sq.frames),
        }
        if grew:
            return (
                diag.WARN,
                "bad input since the last report (" + ", ".join(f"{k} {c[k]}" for k in grew) + ")",
                values,
            )
        return diag.OK, "input ok", values

    def _diag_state(self) -> tuple[int, str, dict]:
        sq = self.seq
        out, cs = sq.out, sq.cs
        code = int(out[CO_FAULT]) if sq.next_k > 0 else int(cs[CS_FAULT])
        mode = MODE_NAMES.get(int(out[CO_MODE]), "?")
        values = {
            "mode": mode,
            "pwm_enabled": bool(out[CO_EN] > 0.5),
            "fault_code": code,
            "fault": FAULT_NAMES.get(code, "?") if code else "",
            "fault_detail": sq.fault_detail if code else "",
            "position_source": (self.sub_est.topic if self.sub_est is not None else "encoder"),
        }
        if sq.tripped:
            code = int(cs[CS_FAULT])
            values.update(
                fault_code=code,
                fault=FAULT_NAMES.get(code, "?"),
                mode="fault",
                pwm_enabled=False,
                fault_detail=sq.fault_detail,
            )
            text = FAULT_NAMES.get(code, "fault") + (
                f": {sq.fault_detail}" if sq.fault_detail else ""
            )
            return diag.ERROR, f"PWM off, latched fault: {text}", values
        return diag.OK, f"{mode}, PWM {'on' if values['pwm_enabled'] else 'off'}", values

    def _on_done(self, msg) -> None:
        if not self.exit_on_done:
            return
        self.done_seq = int(msg.seq)
        if self.seq.next_k > self.done_seq:
            self.state_blocks.flush()
            self.finished = True

    def close(self) -> None:
        if self.context.ok():  # stopped or done: the states kept go out
            self.state_blocks.flush()
        if self.done_seq is not None:
            from rclpy.duration import Duration

            for p in (self.pub_duty, self.pub_state):
                p.wait_for_all_acked(Duration(seconds=10.0))


def main(argv: list[str] | None = None) -> int:
    return main_node("foc_controller_node.node:ControllerNode", "controller", argv)


if __name__ == "__main__":
    sys.exit(main())
