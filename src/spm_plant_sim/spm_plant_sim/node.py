"""spm_plant_sim: the switching-level SPM machine + inverter + sensors as a ROS node.

A thin wrapper around fluxdrive.drive.plant's kernels (plant_initial_frame, plant_advance): the
scenario file gives the machine card, load profile, sensor faults and seed, exactly as for
the in-process runner (fluxdrive.drive.sim.DriveSetup builds both).

Publishes   /drive/frame (PhaseFrame)  /drive/truth (PlantTruth)  /clock  /drive/done (RunDone)
Subscribes  /drive/duty (DutyCommand)

Modes
- lockstep (default, sim time): frame 0 and frame 1 (duty(-1) = PWM off) go out as soon as the
  graph is matched; then DutyCommand(seq = j), computed from frame j, drives the period
  [t_{j+1}, t_{j+2}] and frame j+2 is published at once.  Two frames are in flight, which is
  exactly the one-period computation delay of the timing convention (docs/engine.md), so the
  graph reproduces the in-process runner sample for sample.  After frame N-1 and its duty the
  plant publishes /drive/done = N-1 (latched) and exits.
- paced: the same loop, held to the wall clock at `rate_factor` x real time: frame k is
  published once it is due *and* duty(k-2) has arrived (so a paced run equals a lockstep
  run).  A late host is not a dead one: a controller that answers after the deadline (the
  due time of frame k) but within `watchdog_s` of wall time since its previous duty command
  holds the plant -- the previous duty stays in effect, nothing is simulated meanwhile and
  time slips by the wait (frame k is due when it goes out, no burst of frames to catch up
  with the wall clock); the duty is counted (late_duties) and its lateness recorded: never
  a PWM off, nothing a controller counts as a lost interval.  Only a controller silent for
  `watchdog_s` (no duty command at all) is taken for dead: PWM off (frames flagged
  STATUS_STALE_COMMAND), one log line, until duty commands come back (the controller
  latches its 'watchdog' fault when it sees that).  The clock starts with the first duty
  command (up to `first_duty_timeout_s`, 30 s: processes starting); the plant lets time
  slip when it is itself more than 50 periods late.  The pacing record (lateness of every
  frame against its due time and of every duty command against its deadline, p50/p99/max,
  late duties, skipped duties -- periods the controller never answered because it went on
  with a later frame, run on the previous duty and flagged STATUS_STALE_COMMAND -- slips,
  watchdog trips) is logged as one
  "pacing {json}" line when the plant stops, and while it runs the /diagnostics status
  "<node>: pacing" gives the same for the frames and duties since its last report.  A live
  `rate_factor` change re-anchors the pacing clock at the sample it takes effect (the
  simulated time reached so far is kept), so the next frame follows at the new rate
  without a gap; a paced plant that publishes no frame for `stall_warn_s` of wall time
  says so in one line.

Safe state when the controller is gone (watchdogs):
- lockstep: a duty command that has not come after `duty_timeout_s` of wall time (the
  controller died or hangs; 10 s for the first one) -> the period it would have driven is
  simulated with the PWM off (frame flagged STATUS_STALE_COMMAND), and one more each further
  `duty_timeout_s`, until duty commands come back (a restarted controller picks up at the
  live frame; the skipped duties are dropped if they come late);
- paced: see above (`watchdog_s`);
- stopped before the end of the run (SIGINT/SIGTERM, the launcher stopping the graph): one
  last period with the PWM off is simulated and published (flagged STATUS_STALE_COMMAND,
  acknowledged by the readers in other processes, e.g. a recorder stopped after us), and
  the node logs the frame it stopped at.

Sim time: /clock carries t_k every `clock_decimation` frames (0: no /clock).

Malformed duty commands (counted on /diagnostics, "<node>: commands"): a non-finite duty
drives that period with the PWM off; a duty outside [0, 1] is clamped (as a real modulator
does); a seq that repeats or goes backwards, or names a frame not published yet, is dropped.
Duty commands are obeyed only from the nodes in `allowed_commanders` (default /controller;
fluxdrive_ros.access); others are dropped and counted.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from fluxdrive.core import schema
from fluxdrive.core.machine import DEADTIME_RANGE_S
from fluxdrive.core.schema import param
from fluxdrive.drive.control import CO_DA, CO_DB, CO_DC, CO_EN
from fluxdrive.drive.plant import FR_N, MP_TD, TR_N, plant_advance, plant_initial_frame
from fluxdrive.drive.scenario import ScenarioSettings, load_scenario, scenario_path
from fluxdrive.drive.sim import DriveSetup
from fluxdrive.drive.warm import direct
from fluxdrive_ros.cdr import Codec, Decoder
from fluxdrive_ros.intra import BlockSender, RawPublisher, RawSubscription
from fluxdrive_ros.params import P, config_params, declare, input_durability_param, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from fluxdrive_ros.wire import STATUS_SIMULATED, STATUS_STALE_COMMAND, FrameWire, Stamp, TruthWire
from rclpy.duration import Duration
from rosgraph_msgs.msg import Clock

import flux_drive_msgs.msg as fm
from fluxdrive_ros import access, qos, topics
from fluxdrive_ros import diagnostics as diag


@dataclass
class PlantInput:
    """What the plant simulates."""

    scenario: str = param(
        "",
        unit="",
        doc="scenario YAML (path or a name under config/scenarios): machine card, load, seed, "
        "faults",
        live=False,
    )


@dataclass
class PlantRun:
    """The run: mode, seed, length, the bridge's deadtime, the load."""

    mode: str = param(
        "lockstep",
        unit="",
        doc="lockstep: sim time, one period per duty command; paced: wall clock at rate_factor",
        choices=("lockstep", "paced"),
        live=False,
    )
    duration_s: float = param(
        11.0,
        unit="s",
        doc="run length (paced: 0 = until stopped)",
        range=(0.0, 3600.0),
        live=False,
    )
    deadtime_s: float = param(
        2.0e-6,  # the card's, unless the scenario overrides it
        unit="s",
        doc="inverter deadtime of the simulated bridge",
        range=DEADTIME_RANGE_S,
    )
    load_mode: str = param(
        "profile",
        unit="",
        doc="load torque: the scenario's profile (times load_scale) or a constant load_constant_nm",
        choices=("profile", "constant"),
    )
    load_scale: float = param(
        1.0,
        unit="-",
        doc="factor on the scenario's load profile",
        range=(0.0, 10.0),
    )
    load_constant_nm: float = param(
        0.0,
        unit="N m",
        doc="load torque when load_mode = constant",
        range=(-100.0, 100.0),
    )


@dataclass
class PlantTiming:
    """Pacing and the watchdogs."""

    rate_factor: float = param(
        1.0,
        unit="-",
        doc="paced mode: simulated seconds per wall second",
        range=(0.001, 10.0),
    )
    first_duty_timeout_s: float = param(
        30.0,
        unit="s",
        doc="paced mode: how long the plant waits for the first duty command "
        "(processes starting, code loading) before it runs on with the PWM "
        "off",
        range=(0.0, 3600.0),
    )
    stall_warn_s: float = param(
        2.0,
        unit="s",
        doc="paced mode: one warning line when no frame has been published for "
        "this much wall time beyond its due time (the plant waits for a duty "
        "command, or its loop is starved), one more when frames come again",
        range=(0.01, 3600.0),
    )
    watchdog_s: float = param(
        1.0,
        unit="s",
        doc="paced mode: the controller counts as dead when no duty command at "
        "all has come for this much wall time: PWM off (frames flagged stale)"
        " until duty commands come back, one log line; a duty command late by"
        " less is lateness (the plant waits with the previous duty in effect,"
        " time slips; counted and reported), never a PWM off",
        range=(0.001, 3600.0),
    )
    duty_timeout_s: float = param(
        5.0,
        unit="s",
        doc="lockstep mode: simulate the next period with the PWM off when its "
        "duty command has not come for this much wall time (controller dead "
        "or hung), then one period per timeout until commands come back; 0 = "
        "wait forever",
        range=(0.0, 3600.0),
    )


@dataclass
class PlantGraph:
    """Start-up matching, /clock, progress, exit, frame_id, durability."""

    clock_decimation: int = param(
        10,
        unit="frames",
        doc="publish /clock every N frames (0: never)",
        range=(0, 1000000),
    )
    wait_frame_subscribers: int = param(
        1,
        unit="-",
        doc="matched /drive/frame subscribers needed before the first frame",
        range=(0, 1000),
        live=False,
    )
    wait_duty_publishers: int = param(
        1,
        unit="-",
        doc="matched /drive/duty publishers needed before the first frame",
        range=(0, 100),
        live=False,
    )
    start_delay_s: float = param(
        0.5,
        unit="s",
        doc="wait this long after matching before the first frame (lets the rest "
        "of the graph finish discovery)",
        range=(0.0, 60.0),
        live=False,
    )
    progress_interval_s: float = param(
        0.5,
        unit="s",
        doc="progress line period on stdout (0: none)",
        range=(0.0, 3600.0),
    )
    exit_on_done: bool = param(
        True,
        unit="",
        doc="exit after the run's last frame (after /drive/done)",
    )
    frame_id: str = param(
        "",
        unit="",
        doc="header.frame_id of published frames",
        live=False,
    )


def run_params(sc) -> list[P]:
    """The run: mode, seed, length, the bridge's deadtime, the load."""
    td = sc.machine.deadtime_s if sc.plant_deadtime_s is None else sc.plant_deadtime_s
    run = PlantRun(duration_s=float(sc.duration_s), deadtime_s=float(td))
    seed = P.of(schema.specs(ScenarioSettings)["seed"], int(sc.seed))  # the scenario's key
    return [seed, *config_params(run)]


def timing_params() -> list[P]:
    """Pacing and the watchdogs: rate, first duty, stalls, a dead or hung controller."""
    return config_params(PlantTiming())


def graph_params() -> list[P]:
    """Start-up matching, /clock, progress, exit, frame_id, durability, diagnostics, access."""
    return [
        *config_params(PlantGraph()),
        input_durability_param(),
        diag.PARAM,
        access.param(),
    ]


def param_table(sc) -> list[P]:
    """The plant's declared parameters (description, unit, range; live ones marked)."""
    return run_params(sc) + timing_params() + graph_params()


# paced: a plant late by more than this many periods lets time slip instead of catching up
MAX_CATCH_UP = 50


class PlantNode(FluxNode):
    TIMING_SETTINGS = PlantTiming  # pacing and watchdogs (`./fluxdrive tune` checks by them)

    def __init__(self, name: str = "plant", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        sc = self._scenario()
        self.specs = param_table(sc)
        pv = declare(self, self.specs)
        self.pv = pv
        sc.seed = int(pv["seed"])
        sc.duration_s = float(pv["duration_s"]) or sc.duration_s
        sc.plant_deadtime_s = float(pv["deadtime_s"])
        self.sc = sc
        self.ds = ds = DriveSetup(sc)
        self.n = ds.n if float(pv["duration_s"]) > 0 else 2**62
        self.paced = pv["mode"] == "paced"
        self.pst, self.rng = ds.new_plant()
        self.frame = np.zeros(FR_N)
        self.truth = np.zeros(TR_N)
        self.duty = np.array([0.5, 0.5, 0.5])
        self.mp = ds.mp.copy()
        self._set_load(pv)
        self.stamp = Stamp(ds.ts)
        self._wire(pv)
        self._init_state(pv)
        self.counts = diag.Counters(
            "duty_received",
            "duty_nonfinite",
            "duty_out_of_range",
            "repeated_or_backwards",
            "unexpected_seq",
            "watchdog_trips",
        )
        self._logged = 0
        on_set(self, self.specs, self._apply, lambda: self.k + 1, ds.ts)
        self.guard = access.CommandGuard(
            topics.drive_names(self, list(pv["allowed_commanders"])), topics.DUTY
        )
        self.diag = diag.Diagnostics(self, pv["diagnostics_period_s"])
        self.diag.add("commands", self._diag_commands)
        self._diag_from = 0  # paced: first lateness entry of the next /diagnostics window
        if self.paced:
            self.diag.add("pacing", self._diag_pacing)
        self.get_logger().info(
            f"scenario {sc.name} ({self.sc.source}): {self.n if self.n < 2**62 else 'inf'} "
            f"periods of {ds.ts * 1e6:.0f} us, seed {sc.seed}, {pv['mode']}"
        )
        self._start_timer = self.create_timer(0.05, self._try_start)
        self._pace_timer: Any = None  # an rclpy Timer once paced

    def _scenario(self):
        """The scenario named by the `scenario` parameter (required)."""
        sp = declare(self, config_params(PlantInput()))["scenario"]
        if not sp:
            raise ValueError("parameter 'scenario' (path of a scenario YAML) is required")
        return load_scenario(scenario_path(sp))

    def _wire(self, pv: dict) -> None:
        """Wire formats, the frame/truth/clock/done publishers and the duty subscription."""
        gid = self.graph.id
        self.fw = FrameWire(pv["frame_id"], extra_flags=STATUS_SIMULATED, graph_id=gid)
        self.tw = TruthWire(pv["frame_id"], graph_id=gid)
        self.clock_codec = Codec(topics.T_CLOCK)
        self.duty_dec = Decoder(topics.T_DUTY)
        # every topic relative to the drive's namespace (`__ns:=/a`: /a/drive/frame, /a/clock)
        in_drive = topics.drive_topic
        self.pub_frame = RawPublisher(
            self, fm.PhaseFrame, in_drive(self, topics.FRAME), qos.SAMPLES, stamp=self.stamp
        )
        self.pub_truth = RawPublisher(
            self, fm.PlantTruth, in_drive(self, topics.TRUTH), qos.SAMPLES
        )
        # lockstep: the truth in blocks (paced: each as it comes, for a live view)
        self.truth_blocks = None if self.paced else BlockSender(self.pub_truth, self.stamp)
        self.pub_clock = RawPublisher(self, Clock, in_drive(self, topics.CLOCK), qos.CLOCK)
        self.pub_done = self.create_publisher(fm.RunDone, in_drive(self, topics.DONE), qos.LATCHED)
        # its watchdog's trips and returns, as DriveFault events (not latched: PWM off only
        # until duty commands come back)
        self.pub_fault = self.create_publisher(
            fm.DriveFault, in_drive(self, topics.FAULT), qos.MARKERS
        )
        # drained: a flood of foreign duty commands is refused in a row, not one executor
        # round each (fluxdrive_ros.intra), so it does not cost the paced loop its deadline
        self.sub_duty = RawSubscription(
            self,
            fm.DutyCommand,
            in_drive(self, topics.DUTY),
            self._on_duty,
            qos.reader(pv["input_durability"]),
            drain=256,
            row_callback=self._on_duty_row,
        )

    def _init_state(self, pv: dict) -> None:
        """Stepping, start-up and pacing state (lateness, late duties, watchdogs)."""
        self.k = -1  # index of the last frame published
        self.next_duty = 0  # lockstep: seq of the duty command expected next
        self.pending: dict[int, tuple] = {}
        self.started = False
        self.done = False
        self.t_wall0 = 0.0
        self.t_last_progress = 0.0
        self.t_matched: float | None = None
        self.clock_dec = int(pv["clock_decimation"])
        # paced mode state
        self.duties: dict[int, tuple] = {}  # seq -> (da, db, dc, enable), recent ones
        self.last_duty: tuple | None = None
        self.t_last_duty = 0.0
        self.watchdog_tripped = False
        self.held = False  # paced: waiting for a duty command past its deadline
        self.n_late_duties = 0  # paced: duty commands that came after their deadline
        self.n_skipped_duties = 0  # paced: periods the controller skipped (answered a later one)
        self.enabled = False  # paced: PWM state of the last period (kept for a skipped one)
        self.owed: dict[int, float] = {}  # paced: seq -> deadline (wall) of a duty waited for
        self.duty_lateness: list[float] = []  # paced: arrival - deadline of every duty [s]
        self.t_run0: float | None = None  # paced: wall time of the first duty command
        self.t_pub = np.zeros(4096)  # wall time frame k was published, at k % 4096
        self._diag_duty_from = 0
        self.n_slips = 0
        self.lateness: list[float] = []  # paced: publish time - due time of every frame [s]
        self.t_last_frame = 0.0  # paced: wall time of the last frame published
        self.stalled_since: float | None = None  # paced: the stall line was said
        self._wd_k = -1  # lockstep watchdog: frame index and wall time of the last progress
        self._wd_t = 0.0

    # ----------------------------------------------------------------- parameters
    def _set_load(self, pv) -> None:
        ds = self.ds
        if pv["load_mode"] == "constant":
            self.load_t = np.array([0.0])
            self.load_y = np.array([float(pv["load_constant_nm"])])
        elif pv["load_scale"] == 1.0:
            self.load_t, self.load_y = ds.load_t, ds.load_y
        else:
            self.load_t, self.load_y = ds.load_t, ds.load_y * float(pv["load_scale"])
        # plant_advance without numba's dispatch: always these arrays (the load's made alike)
        self._plant_advance = direct(
            plant_advance,
            self.pst,
            self.mp,
            self.rng,
            self.duty,
            False,
            self.load_t,
            self.load_y,
            ds.load_cfg,
            self.frame,
            self.truth,
        )

    def _apply(self, changes: dict) -> str:
        new = {**self.pv, **changes}
        if "rate_factor" in changes and self.paced and self.started:
            # re-anchor the pacing clock: the simulated time reached at this instant stays
            # where it is, and from here on wall time counts at the new rate (with the old
            # anchor a lower rate put the next frame's due time far in the future)
            now = time.perf_counter()
            sim_s = (now - self.t_wall0) * float(self.pv["rate_factor"])
            self.t_wall0 = now - sim_s / float(new["rate_factor"])
        self.pv = new
        if "deadtime_s" in changes:
            self.mp[MP_TD] = float(new["deadtime_s"])
        if changes.keys() & {"load_mode", "load_scale", "load_constant_nm"}:
            self._set_load(new)
        if "clock_decimation" in changes:
            self.clock_dec = int(new["clock_decimation"])
        return f"applied from frame {self.k + 1}"

    # ----------------------------------------------------------------- start-up
    def _try_start(self) -> None:
        if self.started:
            return
        ok = (
            self.pub_frame.subscription_count() >= self.pv["wait_frame_subscribers"]
            and self.sub_duty.publisher_count() >= self.pv["wait_duty_publishers"]
        )
        now = time.monotonic()
        if not ok:
            self.t_matched = None
            return
        if self.t_matched is None:
            self.t_matched = now
        if now - self.t_matched < self.pv["start_delay_s"]:
            return
        self.started = True
        self._start_timer.cancel()
        self.t_wall0 = time.perf_counter()
        self.t_last_duty = self.t_wall0
        self.get_logger().info(
            f"graph matched ({self.pub_frame.subscription_count()} frame subscribers); starting"
        )
        plant_initial_frame(self.pst, self.mp, self.rng, self.frame, self.truth)
        self._publish(0)
        if self.paced:
            self._pace_timer = self.create_timer(0.001, self._on_pace)
            return
        if self.n > 1:
            # frame 1 comes from duty(-1): PWM off
            self._advance(self.duty, False, 1)
        self._wd_t = time.perf_counter()
        self._wd_timer = self.create_timer(0.05, self._lockstep_watchdog)

    # ----------------------------------------------------------------- stepping
    def _advance(self, duty, enabled: bool, k: int, flags: int = 0) -> None:
        self._plant_advance(
            self.pst,
            self.mp,
            self.rng,
            duty,
            enabled,
            self.load_t,
            self.load_y,
            self.ds.load_cfg,
            self.frame,
            self.truth,
        )
        self._publish(k, flags)

    def _publish(self, k: int, flags: int = 0) -> None:
        if self.paced:
            self._paced_publish(k)
        self.pub_frame.publish_row(self.fw.rc, self.frame, k, flags)  # frame's seq: k
        if self.truth_blocks is not None:  # lockstep: nothing waits for the truth
            self.truth_blocks.add(self.tw.rc, self.truth, k)
        else:
            self.pub_truth.publish(self.tw.pack(self.truth, k, *self.stamp(k)))
        self.k = k
        if self.clock_dec and k % self.clock_dec == 0:
            self.pub_clock.publish(self.clock_codec.pack(*self.stamp(k)))
        if not k & 63:  # the wall clock is read every 64 frames only
            self._progress(k)

    def _paced_publish(self, k: int) -> None:
        """The paced loop's bookkeeping of frame k's publication (wall time)."""
        self.t_last_frame = time.perf_counter()
        self.t_pub[k % 4096] = self.t_last_frame
        if self.stalled_since is not None:
            self.get_logger().info(
                f"pacing: frames again (frame {k}) after "
                f"{self.t_last_frame - self.stalled_since:.2f} s without one"
            )
            self.stalled_since = None

    def _progress(self, k: int) -> None:
        if self.pv["progress_interval_s"] > 0.0:
            now = time.perf_counter()
            if now - self.t_last_progress >= self.pv["progress_interval_s"]:
                self.t_last_progress = now
                self.progress(f"{k + 1} {self.n} {now - self.t_wall0:.3f} {self.ds.ts!r}")

    def _bad_duty(self, kind: str, text: str) -> None:
        self.counts.add(kind)
        if self._logged < 10:
            self._logged += 1
            self.get_logger().warning(
                text + ("" if self._logged < 10 else " (further cases: /diagnostics only)")
            )

    def _on_duty(self, data: bytes) -> None:
        if not self.guard.accept_raw(data):  # not from an allowed commander: ignored
            self._refused()
            return
        # (sec, nsec, seq, graph_id, da, db, dc, enable): graph_id checked already
        self._duty(self.duty_dec.decode(data))

    def _on_duty_row(self, msg: tuple) -> None:
        """A duty command of a controller in this process, as its row (fluxdrive_ros.intra):
        the mark is its codec's commander string."""
        co, seq, rc = msg
        if not self.guard.accept_codec(rc):
            self._refused()
            return
        cmd = co.tolist()
        self._duty((0, 0, seq, 0, cmd[CO_DA], cmd[CO_DB], cmd[CO_DC], cmd[CO_EN] > 0.5))

    def _refused(self) -> None:
        """A duty command not from an allowed commander: ignored, the first three logged."""
        if self.guard.n_rejected <= 3:
            self.get_logger().warning(
                f"duty command dropped ({self.guard.last_rejected}); obeyed only from "
                f"{self.guard.allowed}"
            )

    def _duty(self, v: tuple) -> None:
        """A duty command (sec, nsec, seq, graph_id, da, db, dc, enable) to apply."""
        seq = v[2]
        self.counts.values["duty_received"] += 1
        lo, hi = -1e-9, 1.0 + 1e-9
        if not (lo <= v[4] <= hi and lo <= v[5] <= hi and lo <= v[6] <= hi):
            v = self._odd_duty(v)  # non-finite (a NaN fails every comparison) or beyond [0, 1]
        if seq > self.k:
            self._bad_duty(
                "unexpected_seq",
                f"duty command {seq} answers no published frame (last {self.k}): dropped",
            )
            return
        if self.paced:
            self._paced_duty(seq, (v[4], v[5], v[6], bool(v[7])))
            return
        if self.done:
            return
        if seq < self.next_duty or seq in self.pending:
            self._bad_duty(
                "repeated_or_backwards",
                f"duty command {seq} repeated or backwards (expected {self.next_duty}): dropped",
            )
            return
        if seq > self.next_duty:
            self.pending[seq] = v
            return
        self._lockstep(v)

    def _odd_duty(self, v: tuple) -> tuple:
        """A duty command with a non-finite duty (-> PWM off for its period) or one outside
        [0, 1] (clamped by the modulator, plant_advance): counted and logged."""
        seq, da, db, dc = v[2], v[4], v[5], v[6]
        if not (math.isfinite(da) and math.isfinite(db) and math.isfinite(dc)):
            self._bad_duty(
                "duty_nonfinite",
                f"duty command {seq}: non-finite duty ({da}, {db}, {dc}): PWM off for that period",
            )
            return (v[0], v[1], seq, v[3], 0.5, 0.5, 0.5, False)
        self._bad_duty(
            "duty_out_of_range",
            f"duty command {seq}: duty ({da:g}, {db:g}, {dc:g}) outside [0, 1]: clamped",
        )
        return v

    def _lockstep(self, v: tuple) -> None:
        """Apply duty(seq = next_duty) to frame seq + 2, then any queued successors."""
        seq = v[2]
        duty = self.duty
        while True:
            k = seq + 2
            if k < self.n:
                duty[0], duty[1], duty[2] = v[4], v[5], v[6]
                self._advance(duty, bool(v[7]), k)
            self.next_duty = seq + 1
            if seq >= self.n - 1:
                self._finish()
                return
            queued = self.pending.pop(self.next_duty, None)
            if queued is None:
                return
            v = queued
            seq = v[2]

    def _watchdog_event(self, k: int, text: str) -> None:
        """The watchdog tripped (WATCHDOG, not latched: PWM off until duty commands come
        back) or duty commands came back (FAULT_NONE), as a DriveFault stamped at frame k."""
        m = fm.DriveFault()
        m.header.stamp.sec, m.header.stamp.nanosec = self.stamp(k)
        m.header.frame_id = self.pv["frame_id"]
        m.code = fm.DriveFault.WATCHDOG if self.watchdog_tripped else fm.DriveFault.FAULT_NONE
        m.latched = False
        m.source = self.get_fully_qualified_name()
        m.reason = text
        self.pub_fault.publish(m)

    def _flush_truth(self) -> None:
        """The truth and the frames kept for block readers (the recorder) go out."""
        if self.truth_blocks is not None:
            self.truth_blocks.flush()
        self.pub_frame.flush_rows()

    def _lockstep_watchdog(self) -> None:
        """lockstep: no duty command for duty_timeout_s of wall time -> the period it would
        have driven goes with the PWM off (flagged stale); again each further timeout.
        Also sends the truth kept so far (a slow loop's truth is at most 50 ms late)."""
        if self.done or not self.started:
            return
        self._flush_truth()
        now = time.perf_counter()
        if self.k != self._wd_k:  # the loop moved: a duty command came
            if self.watchdog_tripped:
                self.watchdog_tripped = False
                text = f"duty commands back (seq {self.next_duty - 1}); lockstep resumes"
                self.get_logger().info(text)
                self._watchdog_event(self.k, text)
            self._wd_k, self._wd_t = self.k, now
            return
        lim = float(self.pv["duty_timeout_s"])
        if self.next_duty == 0:  # the first answer may take a while (code loading)
            lim = max(lim, 10.0)
        if lim <= 0.0 or now - self._wd_t < lim:
            return
        j = self.next_duty
        if not self.watchdog_tripped:
            self.watchdog_tripped = True
            self.counts.add("watchdog_trips")
            text = (
                f"watchdog: no duty command {j} for {lim:g} s of wall time (controller gone?); "
                f"PWM off from frame {j + 2}, one period per {lim:g} s until duty commands "
                f"come back"
            )
            self.get_logger().warning(text)
            self._watchdog_event(j + 2, text)
        self.next_duty = j + 1
        if j + 2 < self.n:
            self._advance(np.array([0.5, 0.5, 0.5]), False, j + 2, STATUS_STALE_COMMAND)
        self._wd_k, self._wd_t = self.k, now
        if j >= self.n - 1:
            self._finish()
            return
        v = self.pending.pop(self.next_duty, None)
        if v is not None:
            self._lockstep(v)

    def _on_pace(self) -> None:
        self._pace_step()
        if self.done or self.stalled_since is not None:
            return
        now = time.perf_counter()
        rate = float(self.pv["rate_factor"])
        silent = now - self.t_last_frame - self.ds.ts / rate  # beyond the next frame's period
        if silent >= self.pv["stall_warn_s"]:
            self.stalled_since = self.t_last_frame
            why = (
                f"waiting for duty command {self.k - 1}"
                if self.held or self.last_duty is None
                else "its loop is starved"
            )
            self.get_logger().warning(
                f"pacing: no frame for {now - self.t_last_frame:.2f} s of wall time after frame "
                f"{self.k} (rate_factor {rate:g}, stall_warn_s {self.pv['stall_warn_s']:g}): {why}"
            )

    def _paced_duty(self, seq: int, d: tuple) -> None:
        """paced: file duty(seq) for frame seq + 2 and measure how late it came."""
        now = time.perf_counter()
        ts_wall = self.ds.ts / float(self.pv["rate_factor"])
        deadline = self.owed.pop(seq, None)  # the plant waited for it past its deadline
        if seq + 2 > self.k:  # its period is still to come (else: after a watchdog trip)
            self.duties[seq] = d
            if deadline is None:
                deadline = self.t_wall0 + (seq + 2) * ts_wall  # when frame seq + 2 is due
        if deadline is not None and self.k - seq < len(self.t_pub):
            # the controller's own lateness: two periods from when it could have frame seq
            # (a plant late itself -- its process stalled -- moves the deadline with it)
            deadline = max(deadline, float(self.t_pub[seq % len(self.t_pub)]) + 2.0 * ts_wall)
        if deadline is not None and self.last_duty is not None:  # (the clock starts with
            self.n_late_duties += int(now > deadline)  # the first one: not counted)
            if len(self.duty_lateness) < 2_000_000:
                self.duty_lateness.append(now - deadline)
        if self.last_duty is None:
            self.t_run0 = now  # the paced run proper starts (its clock too)
        if self.last_duty is None or seq >= self.last_duty[0]:
            self.last_duty = (seq, d)
        self.t_last_duty = now
        # back once it answers a frame still to come (not while it works off its backlog)
        if self.watchdog_tripped and seq + 2 > self.k:
            self.watchdog_tripped = False
            text = f"duty commands back (seq {seq}); PWM follows them"
            self.get_logger().info(text)
            self._watchdog_event(seq + 2, text)
        self._pace_step()

    def _pace_step(self) -> None:
        """Advance every period that is due on its duty(k-2); wait for a late one (time
        slips); PWM off when the controller has been silent for watchdog_s."""
        if self.done or not self.started:
            return
        now = time.perf_counter()
        rate = self.pv["rate_factor"]
        ts = self.ds.ts
        due = int((now - self.t_wall0) * rate / ts)
        if due - self.k > MAX_CATCH_UP:  # the plant itself was late (scheduling): time
            self.n_slips += 1  # slips instead of a burst of frames nobody can answer
            self.t_wall0 += (due - self.k - 1) * ts / rate
            due = self.k + 1
        steps = 0
        while self.k < due and steps < 5000:
            k = self.k + 1
            if k >= self.n:
                self._finish()
                return
            lat = now - self.t_wall0 - k * ts / rate  # lateness against the due time
            if not self._pace_period(k, now, ts / rate):
                break
            if len(self.lateness) < 2_000_000:
                self.lateness.append(lat)
            steps += 1
        if len(self.duties) > 64:  # drop duties for frames already simulated
            for old in [j for j in self.duties if j < self.k - 2]:
                del self.duties[old]
        if len(self.owed) > 100_000:  # duties never sent (a controller catching up)
            for old in sorted(self.owed)[:50_000]:
                del self.owed[old]

    def _pace_period(self, k: int, now: float, ts_wall: float) -> bool:
        """Simulate period k (frame k); False while the plant waits for duty(k-2)."""
        off = np.array([0.5, 0.5, 0.5])
        d = self.duties.pop(k - 2, None)
        if k < 2:  # frame 1 comes from duty(-1): PWM off, as in lockstep
            self._advance(off, False, k)
            return True
        if d is not None:
            if self.held:  # the plant waited for it: time slips by the wait (frame k is
                self.held = False  # due now), no burst of frames to catch up with
                self.t_wall0 = now - k * ts_wall
            self.duty[0], self.duty[1], self.duty[2] = d[0], d[1], d[2]
            self.enabled = d[3]
            self._advance(self.duty, d[3], k)
            return True
        if self.last_duty is not None and self.last_duty[0] > k - 2 and not self.watchdog_tripped:
            # the controller answered a later frame: it skipped this one (catching up), so
            # duty(k-2) will not come -- the previous duty stays on, the frame says so
            self.n_skipped_duties += 1
            self._advance(self.duty, self.enabled, k, STATUS_STALE_COMMAND)
            return True
        silent_s = now - self.t_last_duty
        # the first answer may take a while (processes starting, code loading)
        limit_s = float(
            self.pv["watchdog_s" if self.last_duty is not None else "first_duty_timeout_s"]
        )
        if not self.watchdog_tripped and silent_s < limit_s:
            # late, not dead: the previous duty stays in effect while the plant waits
            if self.last_duty is not None and k - 2 not in self.owed:
                self.owed[k - 2] = self.t_wall0 + k * ts_wall  # its deadline
            self.held = True
            return False
        if not self.watchdog_tripped:
            self.watchdog_tripped = True
            self.counts.add("watchdog_trips")
            text = (
                f"watchdog: no duty command at all for {silent_s:.2f} s of wall time "
                f"({'watchdog_s' if self.last_duty is not None else 'first_duty_timeout_s'} "
                f"{limit_s:g}; the controller is dead or stopped, not late); PWM off from "
                f"frame {k} until duty commands come back"
            )
            self.get_logger().warning(text)
            self._watchdog_event(k, text)
        if self.held:  # time slips by the wait: frame k is due now
            self.held = False
            self.t_wall0 = now - k * ts_wall
        self.owed.pop(k - 2, None)
        self.enabled = False
        self._advance(off, False, k, STATUS_STALE_COMMAND)
        return True

    def pacing(self) -> dict:
        """Paced loop timing: lateness of the frames against their due time and of the
        duty commands against their deadline (two periods after the frame they answer went
        out, or the due time of the frame they drive if later), p50/p99/max in periods of
        paced wall time; late duties (after their deadline),
        slips and watchdog trips (controller silent for watchdog_s)."""
        lat = np.array(self.lateness)
        if lat.size == 0:
            return {"frames": 0}
        return {
            **self._lateness_stats(lat, np.array(self.duty_lateness)),
            **self._pacing_totals(),
            # wall time since the first duty command (t_wall0 moves with every slip)
            "wall_s": time.perf_counter() - (self.t_run0 or self.t_wall0),
        }

    def _pacing_totals(self) -> dict:
        return {
            "late_duties": self.n_late_duties,
            "skipped_duties": self.n_skipped_duties,
            "slips": self.n_slips,
            "watchdog_trips": self.counts["watchdog_trips"],
        }

    def _lateness_stats(self, lat: np.ndarray, duty_lat: np.ndarray) -> dict:
        """Lateness of frames against their due time and of duty commands against their
        deadline, in periods of paced wall time."""
        per = self.ds.ts / self.pv["rate_factor"]
        p50, p99 = np.percentile(lat, [50, 99])
        out = {
            "frames": int(lat.size),
            "period_s": per,
            "lateness_p50_periods": float(p50 / per),
            "lateness_p99_periods": float(p99 / per),
            "lateness_max_periods": float(lat.max() / per),
            "late_frames": int((lat > per).sum()),
            "duties": int(duty_lat.size),
        }
        if duty_lat.size:
            d50, d99 = np.percentile(duty_lat, [50, 99])
            out["duty_lateness_p50_periods"] = float(d50 / per)
            out["duty_lateness_p99_periods"] = float(d99 / per)
            out["duty_lateness_max_periods"] = float(duty_lat.max() / per)
        return out

    def _diag_pacing(self) -> tuple[int, str, dict]:
        """paced: the lateness of the frames and duty commands since the last report (a
        window, so a long session's record is not re-sorted every period), with the run's
        late duties, slips and watchdog trips."""
        lat = np.array(self.lateness[self._diag_from :])
        self._diag_from = len(self.lateness)
        duty_lat = np.array(self.duty_lateness[self._diag_duty_from :])
        self._diag_duty_from = len(self.duty_lateness)
        totals = self._pacing_totals()
        if lat.size == 0:
            return diag.OK, "no frame since the last report", {"frames": 0, **totals}
        st = self._lateness_stats(lat, duty_lat)
        duties = (
            f"; duty commands p50 {st['duty_lateness_p50_periods']:.2f} / p99 "
            f"{st['duty_lateness_p99_periods']:.2f} / max "
            f"{st['duty_lateness_max_periods']:.1f} periods late, "
            f"{totals['late_duties']} waited for"
            if duty_lat.size
            else ""
        )
        return (
            diag.OK,
            f"frames p50 {st['lateness_p50_periods']:.2f} / p99 "
            f"{st['lateness_p99_periods']:.2f} / max {st['lateness_max_periods']:.1f} periods "
            f"late over {st['frames']} frames" + duties,
            {**st, **totals},
        )

    def _diag_commands(self) -> tuple[int, str, dict]:
        c = self.counts
        c.set("commands_rejected", self.guard.n_rejected)
        grew = c.grew(
            "duty_nonfinite",
            "duty_out_of_range",
            "repeated_or_backwards",
            "unexpected_seq",
            "commands_rejected",
        )
        values = {
            **c.report(),
            **self.guard.values(),
            "last_frame": self.k,
            "mode": self.pv["mode"],
        }
        if self.watchdog_tripped:
            return diag.ERROR, "watchdog: no duty command in time, PWM off", values
        if grew:
            return (
                diag.WARN,
                "bad duty commands since the last report ("
                + ", ".join(f"{k} {c[k]}" for k in grew)
                + ")",
                values,
            )
        return diag.OK, "commands ok", values

    # ----------------------------------------------------------------- end
    def _finish(self) -> None:
        if self.done:
            return
        self.done = True
        if self._pace_timer is not None:
            self._pace_timer.cancel()
        el = time.perf_counter() - self.t_wall0
        sim = (self.k + 1) * self.ds.ts
        self.progress(f"{self.k + 1} {self.n} {el:.3f} {self.ds.ts!r}")
        self.get_logger().info(
            f"done: {self.k + 1} frames, {sim:.3f} s simulated in {el:.2f} s wall "
            f"(real-time factor {sim / max(el, 1e-9):.3f})"
        )
        if self.paced:
            self._log_pacing()
        self._flush_truth()
        msg = fm.RunDone()
        msg.header.stamp.sec, msg.header.stamp.nanosec = self.stamp(self.k)
        msg.seq = self.k
        msg.graph_id = self.graph.id
        self.pub_done.publish(msg)
        # one 10 s deadline for all: a reader that died (SIGKILL) stays matched, unacking,
        # until its participant's lease runs out
        t_end = time.monotonic() + 10.0
        for p in (self.pub_frame, self.pub_truth, self.pub_done):
            p.wait_for_all_acked(Duration(seconds=max(0.0, t_end - time.monotonic())))
        if self.pv["exit_on_done"]:
            # keep the latched /drive/done readable for a moment (late readers)
            self._exit_timer = self.create_timer(0.5, self._exit)

    def _exit(self) -> None:
        self._exit_timer.cancel()
        self.finished = True

    def close(self) -> None:
        """Stopped before the end of the run: the bridge is switched off -- one last period
        with the PWM off, published (flagged STATUS_STALE_COMMAND) and acknowledged by the
        readers still there, so that a recording ends in the safe state."""
        if not self.started or self.done:
            return
        self.done = True
        k = self.k + 1
        ts = self.ds.ts
        if k < self.n and self.context.ok():
            try:
                self._advance(np.array([0.5, 0.5, 0.5]), False, k, STATUS_STALE_COMMAND)
                self._flush_truth()
                for p in (self.pub_frame, self.pub_truth):
                    p.wait_for_all_acked(Duration(seconds=2.0))
            except Exception as exc:  # noqa: BLE001 - shutting down anyway
                self.log(f"could not publish the final PWM-off frame: {exc}", "warning")
        self.log(
            f"stopped before the end of the run: PWM off from frame {self.k} "
            f"(t = {self.k * ts:.4f} s); {self.k + 1} frames published"
        )
        if self.paced:
            self._log_pacing()

    def _log_pacing(self) -> None:
        import json

        self.log("pacing " + json.dumps(self.pacing()))


def main(argv: list[str] | None = None) -> int:
    return main_node("spm_plant_sim.node:PlantNode", "plant", argv)


if __name__ == "__main__":
    sys.exit(main())
