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

import numpy as np
from fluxdrive.core.machine import load_machine
from fluxdrive.drive.control import (
    CO_EN,
    CO_FAULT,
    CO_MODE,
    CS_FAULT,
    FAULT_NAMES,
    MODE_NAMES,
    ControllerConfig,
    control_ranges,
    host_params,
)
from fluxdrive.drive.observers import ES_N
from fluxdrive.drive.plant import FR_N
from fluxdrive.drive.scenario import CONFIG_DIR, RPM, load_scenario, scenario_path
from fluxdrive.drive.sequencer import ControlSequencer
from fluxdrive.drive.sim import DriveSetup
from fluxdrive.io.messages import ReferenceWire
from fluxdrive_ros.intra import RawPublisher, RawSubscription
from fluxdrive_ros.params import P, declare, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from fluxdrive_ros.wire import ControlWire, EstimateWire, FrameWire, Stamp

import flux_drive_msgs.msg as fm
from flux_drive_msgs.srv import ResetFault
from fluxdrive_ros import access, params, qos, topics
from fluxdrive_ros import diagnostics as diag

# ControllerConfig field -> (description, unit); ranges from fluxdrive.drive.control.control_ranges
DOCS = {
    "current_bandwidth_hz": ("-3 dB bandwidth of the dq current loops (gains re-designed)", "Hz"),
    "speed_bandwidth_hz": (
        "target -3 dB bandwidth of the speed loop (gains re-designed; "
        "lower if the peaking limit binds)",
        "Hz",
    ),
    "peak_limit_db": (
        "robustness limit of the loop design: closed-loop peaking of the current and speed loops",
        "dB",
    ),
    "current_limit_pu": ("|i_q*| limit, per unit of rated current", "pu"),
    "angle_advance_periods": ("inverse-Park angle advance, in periods of w^", "periods"),
    "deadtime_comp_s": ("deadtime feed-forward on the duties (0 = off)", "s"),
    "decoupling": ("cross-coupling and back-EMF feed-forward on", ""),
    "align_time_s": ("sensorless start: alignment time", "s"),
    "align_current_pu": ("sensorless start: alignment d current", "pu"),
    "if_current_pu": ("sensorless start: I-f ramp current", "pu"),
    "if_accel_rpm_s": ("sensorless start: I-f ramp acceleration", "rpm/s"),
    "handover_rpm": ("I-f -> observer handover speed", "rpm"),
    "handback_rpm": ("observer -> I-f hand-back speed (below handover)", "rpm"),
    "handover_dwell_s": (
        "estimate valid and agreeing with the I-f ramp this long before handover",
        "s",
    ),
    "handover_agree_lpf_hz": (
        "handover criterion: estimate vs I-f ramp compared low-passed at "
        "this cut-off (0 = per sample)",
        "Hz",
    ),
    "handover_timeout_s": (
        "I-f ramp at the handover speed this long without a handover "
        "latches 'start-up failed' (0 = wait for ever)",
        "s",
    ),
    "encoder_pll_hz": ("encoder tracking-PLL bandwidth", "Hz"),
    "speed_feedback_lpf_hz": ("display low-pass of the speed feedback", "Hz"),
    "speed_observer_pll_hz": (
        "driving observer's PLL bandwidth assumed by the speed-loop design; 0 = ideal feedback",
        "Hz",
    ),
    "speed_observer_damping": ("driving observer's PLL damping assumed by the design", ""),
    "speed_observer_lpf_hz": ("driving observer's speed LPF assumed by the design", "Hz"),
    "overcurrent_pu": ("instantaneous over-current trip, per unit of rated current", "pu"),
    "overspeed_pu": ("over-speed trip, per unit of rated speed", "pu"),
    "vdc_min_v": ("DC-bus under-voltage trip", "V"),
    "vdc_max_v": ("DC-bus over-voltage trip", "V"),
    "invalid_timeout_s": ("loss-of-lock trip: estimate invalid this long in closed loop", "s"),
    "i2t_limit_pu2s": ("I2t trip: integral of ((i/I_rated)^2 - 1) dt", "pu^2 s"),
    "r_hat_ohm": ("controller's stator resistance R^", "ohm"),
    "l_hat_h": ("controller's stator inductance L^", "H"),
    "lambda_hat_vs": ("controller's magnet flux lambda^", "V s"),
    "reference_timeout_s": (
        "split mode: the drive turns PWM off and latches 'watchdog' when no current "
        "reference comes for this long",
        "s",
    ),
}
# ControllerConfig fields that are not live kernel parameters: where the loop runs
SPLIT_FIELDS = ("mode", "decimation", "host_delay_samples")
# wall-clock grace for the very first estimate (a starting observer process, compilation)
FIRST_ESTIMATE_WALL_S = 30.0
# parameters of the node, not of ControllerConfig
NODE_LEVEL = {
    "control_mode",
    "decimation",
    "speed_ref_mode",
    "speed_ref_rpm",
    "position_timeout_s",
    "position_wall_timeout_s",
    "max_resyncs",
    "resync_window_s",
}
# None-able fields: ROS parameters cannot be None; 0.0 stands for None
NONE_AS_ZERO = frozenset({"speed_observer_pll_hz"})


def config_params(cfg: ControllerConfig, card) -> list[P]:
    return params.config_params(
        cfg,
        card,
        DOCS,
        control_ranges(card, int(cfg.decimation)),
        skip=("position_source", *SPLIT_FIELDS),
        none_as_zero=NONE_AS_ZERO,
    )


def to_config(cfg: ControllerConfig, values: dict) -> ControllerConfig:
    """cfg with parameter values applied (0.0 -> None where ROS cannot say None)."""
    kw = {}
    names = {f.name for f in dataclasses.fields(cfg)}
    for k, v in values.items():
        if k not in names:
            continue
        if k in NONE_AS_ZERO and v == 0.0:
            v = None
        kw[k] = v
    return dataclasses.replace(cfg, **kw)


class ControllerNode(FluxNode):
    def __init__(self, name: str = "controller", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        first = declare(
            self,
            [
                P(
                    "scenario",
                    "",
                    "scenario YAML (path or a name under config/scenarios): machine "
                    "card, controller defaults, speed profile and injections",
                    read_only=True,
                ),
                P(
                    "machine",
                    str(CONFIG_DIR / "machines" / "default_spm.yaml"),
                    "machine card YAML when no scenario is given",
                    read_only=True,
                ),
            ],
        )
        sp, mpath = first["scenario"], first["machine"]
        if sp:
            sc = load_scenario(scenario_path(sp))
            card = sc.machine
            cfg = sc.control
            ds = DriveSetup(sc)
            self.w_ref_profile, self.id_inj = ds.w_ref, ds.id_inj
            driving = sc.driving
        else:
            card = load_machine(mpath)
            cfg = ControllerConfig()
            self.w_ref_profile, self.id_inj = np.zeros(1), np.zeros(1)
            driving = "encoder"
        src = declare(
            self,
            [
                P(
                    "position_source",
                    cfg.position_source,
                    "angle/speed feedback: the encoder or an observer's estimate topic",
                    choices=("encoder", "estimate"),
                    read_only=True,
                ),
                P(
                    "estimate_topic",
                    topics.rel(
                        topics.estimate_topic(driving if driving != "encoder" else "flux_measured")
                    ),
                    "RotorEstimate topic of the driving observer (position_source = estimate; "
                    "relative: in the drive's namespace)",
                    read_only=True,
                ),
                P(
                    "control_mode",
                    cfg.mode,
                    "where the current loop runs: host (this node, duties out) or split "
                    "(the drive, current references out on /drive/current_ref)",
                    choices=("host", "split"),
                    read_only=True,
                ),
                P(
                    "decimation",
                    int(cfg.decimation),
                    "PWM periods per frame: the node steps at decimation x the card's PWM period",
                    "",
                    1,
                    64,
                    read_only=True,
                ),
            ],
        )
        self.split = src["control_mode"] == "split"
        self.decimation = int(src["decimation"])
        d = self.decimation
        self.w_ref_profile, self.id_inj = self.w_ref_profile[::d], self.id_inj[::d]
        # every card-derived default (bus window, bandwidths, handover) as a concrete value:
        # ROS parameters cannot say "derive it"
        cfg = dataclasses.replace(cfg, position_source=src["position_source"]).resolved(card)
        self.card = card
        self.specs = config_params(cfg, card) + [
            P(
                "speed_ref_mode",
                "profile",
                "speed reference: the scenario's profile or the constant speed_ref_rpm (live)",
                choices=("profile", "constant"),
            ),
            P("speed_ref_rpm", 0.0, "constant mechanical speed reference (live)", "rpm", -1e5, 1e5),
            P(
                "position_timeout_s",
                0.05,
                "safe state (PWM off, latched 'stale input') when "
                "the driving estimate of a frame has not come while frames this much sample "
                "time later have (live)",
                "s",
                1e-4,
                10.0,
            ),
            P(
                "position_wall_timeout_s",
                2.0,
                "safe state when the driving estimate of a "
                "waiting frame has not come for this much wall time (lockstep graphs, where "
                "the plant waits for us; 0: off) (live)",
                "s",
                0.0,
                3600.0,
            ),
            P(
                "max_resyncs",
                0,
                "lost intervals (PWM switched off by the power stage's watchdog: no duty "
                "command from this controller for its wall-time limit) tolerated within "
                "resync_window_s; one more latches the fault 'watchdog' (0: the first "
                "latches -- the plant's watchdog takes only a silent controller for dead, "
                "a late one is lateness)",
                "",
                0,
                1000,
                read_only=True,
            ),
            P(
                "resync_window_s",
                10.0,
                "sample-time window of max_resyncs",
                "s",
                0.01,
                3600.0,
                read_only=True,
            ),
        ]
        pv = declare(self, self.specs)
        common = declare(
            self,
            [
                *params.frame_input_params(),
                P(
                    "frame_id",
                    "",
                    "header.frame_id of ControllerState and DutyCommand (the access "
                    "mark travels in DutyCommand.commander)",
                    read_only=True,
                ),
                diag.PARAM,
                P(
                    "allowed_operators",
                    list(access.DEFAULT_OPERATORS),
                    "nodes (fully qualified "
                    "names) whose ~/reset_fault requests are obeyed; '*' = anyone",
                    read_only=True,
                ),
            ],
        )
        self.allowed_operators = list(common["allowed_operators"])
        self.pv = pv
        self.cfg = to_config(cfg, pv)
        self.cp = self._params(self.cfg)
        self.sensorless = self.cfg.position_source == "estimate"
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
        # pairing, stale-input trips, lost-interval re-synchronisation: the engine's
        self.rw = ReferenceWire(
            common["frame_id"],
            commander=access.mark(self.get_fully_qualified_name(), topics.CURRENT_REF),
            graph_id=self.graph.id,
        )
        self.seq = ControlSequencer(
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
        )
        self.counts = diag.Counters(*self.seq.counts)
        self.counts.values = self.seq.counts
        self.done_seq: int | None = None
        self.exit_on_done = common["exit_on_done"]
        self._set_ref(pv)
        in_drive = topics.drive_topic
        if self.split:
            self.pub_duty = RawPublisher(
                self, fm.CurrentReference, in_drive(self, topics.CURRENT_REF), qos.SAMPLES
            )
        else:
            self.pub_duty = RawPublisher(
                self, fm.DutyCommand, in_drive(self, topics.DUTY), qos.SAMPLES
            )
        self.pub_state = RawPublisher(
            self, fm.ControllerState, in_drive(self, topics.CONTROLLER_STATE), qos.SAMPLES
        )
        self.sub_frame = RawSubscription(
            self,
            fm.PhaseFrame,
            topics.in_drive(self, common["frame_topic"]),
            self._on_frame,
            qos.reader(common["input_durability"]),
        )
        self.sub_est = None
        if self.sensorless:
            self.sub_est = RawSubscription(
                self,
                fm.RotorEstimate,
                topics.in_drive(self, src["estimate_topic"]),
                self._on_est,
                qos.reader(common["input_durability"]),
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
        self.reset_service = self.resolve_service_name("~/reset_fault")
        self.create_service(ResetFault, self.reset_service, self._on_reset)
        on_set(self, self.specs, self._apply, lambda: self.seq.next_k, card.ts_s)
        self.diag = diag.Diagnostics(self, common["diagnostics_period_s"])
        self.diag.add("input", self._diag_input)
        self.diag.add("state", self._diag_state)
        if self.sensorless:
            self.create_timer(0.1, self._check_wall_timeout)
        self.get_logger().info(
            "position from "
            + (src["estimate_topic"] if self.sensorless else "the encoder")
            + f"; current loop {self.cfg.current_bandwidth_hz:g} Hz, speed loop "
            f"{self.cfg.speed_bandwidth_hz:g} Hz"
        )

    # ----------------------------------------------------------------- parameters
    def _params(self, cfg: ControllerConfig) -> np.ndarray:
        """The kernel's row at this node's sample time: split, the host's half of the
        PWM-rate design; host mode at D > 1, the loops designed for the sample rate."""
        d = self.decimation
        if self.split:
            return host_params(dataclasses.replace(cfg, mode="split").to_params(self.card), d)
        if d > 1:
            card = dataclasses.replace(self.card, pwm_hz=self.card.pwm_hz / d)
            return dataclasses.replace(cfg, mode="host", decimation=1).to_params(card)
        return cfg.to_params(self.card)

    def _set_ref(self, pv) -> None:
        self.seq.set_timeouts(pv["position_timeout_s"], pv["position_wall_timeout_s"])
        self.seq.const_ref = (
            pv["speed_ref_rpm"] * RPM if pv["speed_ref_mode"] == "constant" else None
        )

    def _apply(self, changes: dict) -> str:
        new = {**self.pv, **changes}
        ctrl = {k: v for k, v in changes.items() if k not in NODE_LEVEL}
        if ctrl:
            cfg = to_config(self.cfg, ctrl)
            cp = self._params(cfg)  # ConfigError (a ValueError) -> rejected
            self.cp[:] = cp
            self.cfg = cfg
        self.pv = new
        self._set_ref(new)
        return f"applied from sample {self.seq.next_k}"

    # ----------------------------------------------------------------- samples
    def _on_frame(self, data: bytes) -> None:
        fr = np.empty(FR_N)
        self.seq.on_frame(self.fw.unpack(data, fr), fr)

    def _on_est(self, data: bytes) -> None:
        es = np.empty(ES_N)
        self.seq.on_estimate(self.ew.unpack(data, es), es)

    def _publish(self, k: int, out: np.ndarray) -> None:
        sec, nsec = self.stamp(k)
        if self.split:
            self.pub_duty.publish(self.rw.pack(self.seq.ref, k, sec, nsec))
        else:
            self.pub_duty.publish(self.cw.pack_duty(out, k, sec, nsec))
        self.pub_state.publish(self.cw.pack_state(out, k, sec, nsec))
        if out[CO_FAULT] != self._fault_code:  # latched or cleared at this sample
            self._fault_event(k, out, sec, nsec)
        if self.done_seq is not None and k >= self.done_seq:
            self.finished = True

    def _fault_event(self, k: int, out: np.ndarray, sec: int, nsec: int) -> None:
        """A DriveFault on drive/fault: the code latched at sample k (PWM off), or
        FAULT_NONE once a reset cleared it."""
        code = int(out[CO_FAULT])
        before = int(self._fault_code)
        self._fault_code = out[CO_FAULT]
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
            self.finished = True

    def close(self) -> None:
        if self.done_seq is not None:
            from rclpy.duration import Duration

            for p in (self.pub_duty, self.pub_state):
                p.wait_for_all_acked(Duration(seconds=10.0))


def main(argv: list[str] | None = None) -> int:
    return main_node("foc_controller_node.node:ControllerNode", "controller", argv)


if __name__ == "__main__":
    sys.exit(main())
