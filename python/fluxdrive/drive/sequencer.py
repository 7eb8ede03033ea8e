"""The controller's sequencing outside the kernel: which frame is answered with which
estimate, when an input counts as stale, and how the drive picks up after the power stage
switched its PWM off on its own (a watchdog) -- the part of a drive's control task that
surrounds `controller_step`.  No ROS: the controller node only feeds it decoded messages and
publishes what it emits; tests drive it directly (tests/test_sequencer.py).

Pairing.  Samples are answered strictly in order k = 0, 1, 2, ...: frame k with (sensorless)
the driving observer's estimate k.  A frame whose seq repeats or goes backwards is dropped; a
jump skips the missing samples (frames lost upstream are never waited for).

Stale input (latched fault "stale input", PWM off until an explicit reset; every later frame
is answered at once with the PWM off):
- the estimate of a frame has not come while frames `position_timeout_s` of sample time
  later are already here (a paced plant or a bench keeps producing frames) and it has been
  waited for `min_wait_s` of wall time -- once a first estimate has come and not while
  catching up after a lost interval (a backlog of queued frames says nothing about time);
- the estimate of the waiting frame has not come for `position_wall_timeout_s` of wall time
  (a lockstep plant waits for us, so sample time stands still; `first_estimate_wall_s` for
  the very first estimate: an observer process starting, code compiling; 10 s while this
  controller is catching up after a stall of its own -- a sample its DDS reader dropped
  while the process stood still is sent again only at the writer's next heartbeat);
- `position_timeout_s` worth of consecutive repeated/backwards frames (e.g. a restarted
  source counting from 0 again).

Lost intervals (the drive resumes as a real one does).  Frame k was produced with duty(k-2)
(one period of computation, one of application).  When duty(k-2) asked for PWM on but frame
k says the bridge did not switch, the power stage's watchdog has switched it off -- this
controller stalled (a scheduling hiccup, GC, a stopped process) or its commands were lost.
The interval is lost, not the rotor's angle: the controller does not count the gap as loss of
observer lock.  On every lost frame it re-synchronises:
- flying restart: the driving estimate is valid and the rotor turns above the handover
  speed -- closed loop continues on the estimate; the current integrators start from zero
  (the decoupling feed-forward carries the back-EMF), the speed integrator keeps the torque
  it carried, the invalid-estimate timer is cleared;
- otherwise back through the start-up: align, I-f ramp, handover (a braked rotor stops
  within the gap; no observer can see a stopped rotor).
Catching up after a stall, it goes on with the newest frame whose estimate is here (the
queued ones in between would be answered too late to be applied; counted as skipped).
One log line when an interval starts, one when the PWM is back, one when the drive is in
closed loop again.  More than
`max_resyncs` lost intervals within `resync_window_s` of sample time latch the fault
"watchdog" with that reason (a power stage that keeps timing out is not a hiccup).

Every latched fault -- the kernel's protection trips and the ones above -- is logged once,
with its detail (values and limits), through the `log(level, text)` callback.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from fluxdrive.drive.control import (
    CO_EN,
    CO_MODE,
    CO_N,
    CO_W_FB,
    CP_HANDOVER,
    CP_P,
    CS_FAULT,
    CS_ID_I,
    CS_INV_T,
    CS_IQ_I,
    CS_MODE,
    CS_N,
    FAULT_NAMES,
    FAULT_STALE_INPUT,
    FAULT_WATCHDOG,
    MODE_CLOSED_LOOP,
    MODE_FAULT,
    RF_N,
    controller_clear_fault,
    controller_reset,
    controller_step,
    host_reference_step,
    trip_values,
)
from fluxdrive.drive.observers import ES_N, ES_VALID, ES_W
from fluxdrive.drive.plant import FR_EN, FR_N

# what the sequencer counts (`counts`), in this order
COUNTS = (
    "frames",
    "estimates",
    "repeated_or_backwards",
    "missing_frames",
    "late_estimates",
    "stale_trips",
    "lost_frames",
    "lost_intervals",
    "skipped_frames",
    "flying_restarts",
    "restarts",
    "faults_latched",
)
Log = Callable[[str, str], None]  # (level: "info" | "warning" | "error", text)
Emit = Callable[[int, np.ndarray], None]  # (seq, CO_* row) for every answered frame


class ControlSequencer:
    """Pairs frames with estimates, runs `controller_step`, trips on stale input and
    re-synchronises after lost intervals.  Feed it `on_frame` / `on_estimate`, call
    `check_wall` now and then (e.g. every 0.1 s); it calls `emit(seq, CO_* row)` for every
    frame it answers, in order."""

    def __init__(
        self,
        cp: np.ndarray,
        ts_s: float,
        sensorless: bool,
        emit: Emit,
        log: Log,
        w_ref_profile: np.ndarray | None = None,
        id_inj: np.ndarray | None = None,
        position_timeout_s: float = 0.05,
        position_wall_timeout_s: float = 2.0,
        first_estimate_wall_s: float = 30.0,
        depth: int = 10000,
        max_resyncs: int = 5,
        resync_window_s: float = 10.0,
        min_wait_s: float = 0.25,
        split: bool = False,
        own_rows: bool = False,
    ):
        self.cp = cp
        # split mode: answer with the host's reference (`ref`, RF_*; host_reference_step at
        # the sample time ts_s) instead of duties; `out` keeps the host's CO_* row
        self.split = split
        self.ref = np.zeros(RF_N)
        self.ts = ts_s
        self.sensorless = sensorless
        self.emit = emit
        self.log = log
        self.w_ref_profile = np.zeros(1) if w_ref_profile is None else w_ref_profile
        self.id_inj = np.zeros(0) if id_inj is None else id_inj
        self.const_ref: float | None = None
        self.first_estimate_wall_s = first_estimate_wall_s
        self.depth = depth
        self.max_resyncs = max_resyncs
        self.resync_window_s = resync_window_s
        self.min_wait_s = min_wait_s
        self.self_stall_s = 0.5  # check_wall called this much later: this process stalled
        # after a stall of this process: samples its DDS reader dropped meanwhile come again
        # only at the writer's next heartbeat (seconds); the wall limit while catching up
        self.catch_up_wall_s = 10.0
        self._last_check = 0.0
        self._caught_up_by = 0.0  # wall time until which a stall of our own excuses waiting
        self._init_frame_watch()
        self.set_timeouts(position_timeout_s, position_wall_timeout_s)
        self.cs = np.zeros(CS_N)
        controller_reset(self.cs)
        self.out = np.zeros(CO_N)
        self.no_est = np.zeros(ES_N)
        self._step = self._kernel(own_rows)
        self.spare: list[np.ndarray] = []  # rows of answered frames, for the caller's next ones
        self.frames: dict[int, np.ndarray] = {}
        self.ests: dict[int, np.ndarray] = {}
        self.next_k = 0
        self.max_seq = -1  # highest frame seq received
        self.rejected_run = 0  # consecutive dropped (repeated/backwards) frames
        self.wait_k = -1  # sample whose estimate is being waited for since t_wait (wall)
        self.t_wait = 0.0
        self.fault_detail = ""
        self._fault_logged = False
        self.enables: dict[int, bool] = {}  # seq -> PWM enable of the duty sent for it
        self.lost_run = 0  # consecutive lost frames (0: none in progress)
        self.lost_first = -1
        self.recover_from = -1  # first lost frame of a recovery not yet back in closed loop
        self.resync_at: list[int] = []  # frames at which lost intervals began
        self.finished_k = -1  # last frame answered
        self.counts = dict.fromkeys(COUNTS, 0)

    def _kernel(self, own_rows: bool) -> Callable[..., object]:
        """controller_step; for a caller whose every frame is a float64 row of FR_N and every
        estimate one of ES_N (own_rows), its compiled overload without numba's dispatch."""
        if not own_rows:
            return controller_step
        from fluxdrive.drive.warm import direct

        fr = np.zeros(FR_N)
        return direct(controller_step, self.cs, self.cp, fr, self.no_est, 0.0, 0.0, self.out)

    # ------------------------------------------------------------------ settings
    def set_timeouts(self, position_timeout_s: float, position_wall_timeout_s: float) -> None:
        self.n_pos_timeout = max(1, round(position_timeout_s / self.ts))
        self.wall_timeout_s = position_wall_timeout_s

    @property
    def tripped(self) -> bool:
        return self.cs.item(CS_MODE) == MODE_FAULT

    # ------------------------------------------------------------------ inputs
    def on_frame(self, k: int, fr: np.ndarray) -> None:
        """Frame k (an FR_* row; kept, not copied)."""
        c = self.counts
        c["frames"] += 1
        nxt = self.next_k
        if (
            k == self.max_seq + 1
            and not self.ests
            and (nxt in self.frames if self.frames else k == nxt)
            and self._in_step()
        ):
            # lockstep: the next frame in order while next_k waits for its estimate --
            # `_run` would only wait on
            self.rejected_run = 0
            self.max_seq = k
            self.frames[k] = fr
            self._waiting()
            return
        if k < self.next_k or k in self.frames:  # repeated or backwards: dropped
            c["repeated_or_backwards"] += 1
            self.rejected_run += 1
            if self.rejected_run == 1 and c["repeated_or_backwards"] <= 10:
                self.log(
                    "warning", f"frame {k} repeated or backwards (expected {self.next_k}): dropped"
                )
            if self.rejected_run >= self.n_pos_timeout and not self.tripped:
                self.trip_stale(
                    f"{self.rejected_run} consecutive frames repeated or "
                    f"backwards (last {k}, expected {self.next_k})"
                )
            if self.tripped:
                self._answer(k, fr, self.no_est)  # PWM off, whatever the seq
            return
        self.rejected_run = 0
        if k > self.max_seq:
            self.max_seq = k
        self.frames[k] = fr
        if len(self.frames) > self.depth:  # waiting long for the first estimate
            del self.frames[min(self.frames)]
            c["missing_frames"] += 1
        self._run()

    def on_estimate(self, k: int, es: np.ndarray) -> None:
        """The driving observer's estimate k (an ES_* row; copied if kept)."""
        self.counts["estimates"] += 1
        frames = self.frames
        if k == self.next_k and k in frames and not self.ests and self.sensorless:
            # lockstep: the estimate of the frame waiting -- answered as `_run` does; then
            # it would wait for the next frame's estimate
            self._answer(k, frames.pop(k), es)
            self.next_k = k + 1
            if not frames:
                return
            if self.next_k in frames and self._in_step():
                self._waiting()
                return
            self._run()
            return
        if k < self.next_k:  # its frame was answered already (late, stale trip) or lost
            self.counts["late_estimates"] += 1
            return
        if self.counts["estimates"] == 1 and k > self.next_k:
            self._before_first_estimate(k)
        self.ests[k] = es.copy()
        if len(self.ests) > self.depth:  # estimates of frames that never came
            for j in sorted(self.ests)[: len(self.ests) - self.depth]:
                del self.ests[j]
        self._run()

    def _before_first_estimate(self, k: int) -> None:
        """The first estimate to come is frame k's, while frames before k are here: their
        estimates went out before this reader matched the observer's writer (a controller
        restarted at the live samples reads volatile; one started late gets a writer's
        history from some sample on), and estimates come in order, so they never will.
        Those frames are skipped (counted), not waited for until the wall-time timeout
        latches "stale input"."""
        old = [j for j in self.frames if j < k]
        for j in old:
            del self.frames[j]
        self.counts["skipped_frames"] += len(old)
        self.next_k = k

    def _in_step(self) -> bool:
        """`_run` would just wait for next_k's estimate (its frame being here): not tripped,
        no sample timeout possible yet (frames past it < the limit, the next one counted)."""
        return (
            self.sensorless
            and self.cs.item(CS_MODE) != MODE_FAULT  # not tripped
            and self.max_seq + 1 - self.next_k < self.n_pos_timeout
            and len(self.frames) < self.depth
        )

    def _waiting(self) -> None:
        """What `_run` -> `_sample_timeout` does while next_k waits for its estimate."""
        if self.wait_k != self.next_k:
            self.wait_k = self.next_k
            self.t_wait = time.monotonic()

    def check_wall(self, now: float | None = None) -> None:
        """Wall-clock timeout of the estimate the sequence is waiting for; call it every
        0.1 s or so -- a call more than 0.5 s after the previous one means this process was
        stalled itself, and that time does not count as waiting."""
        now = time.monotonic() if now is None else now
        self._watch_frames(now)
        if not self.sensorless:
            self._last_check = now
            return
        if now - self._last_check > self.self_stall_s and self._last_check > 0.0:
            self.t_wait += now - self._last_check  # we were stalled ourselves: not counted
            self._caught_up_by = now + self.catch_up_wall_s
        self._last_check = now
        lim = self.wall_timeout_s
        if lim > 0.0 and self.counts["estimates"] == 0:  # the first one may take a while
            lim = max(lim, self.first_estimate_wall_s)
        if lim > 0.0 and now < self._caught_up_by:  # we stalled: a repair is on its way
            lim = max(lim, self._caught_up_by - self.t_wait)
        if (
            self.tripped
            or self.wait_k != self.next_k
            or self.next_k not in self.frames
            or self.next_k in self.ests
        ):
            return
        waited = now - self.t_wait
        if self._sample_timeout(self.next_k):
            self._run()
            return
        if lim > 0.0 and waited > lim:
            self.trip_stale(
                f"no position estimate for frame {self.next_k} for {waited:.1f} s of wall time"
            )
            self._run()

    def _init_frame_watch(self) -> None:
        """No frame at all for frame_silence_s (wall time, our own stalls not counted): one
        line saying so, one when frames come again (docs/graph.md, "Limit at high frame
        rates")."""
        self.frame_silence_s = 5.0
        self._frames_seen = 0  # counts["frames"] at the last check
        self._silent_since = 0.0  # wall time of the last check that saw a new frame
        self._silence_logged = False

    def _watch_frames(self, now: float) -> None:
        """Frames stopped coming mid-run (after a first one): say so once after
        frame_silence_s of wall time, and again when they come back.  A controller resumed
        after a stop can stand here for long: a frame its DDS reader dropped meanwhile is
        held, with every later one (in-order delivery), until the writer resends it."""
        n = self.counts["frames"]
        if n != self._frames_seen:
            if self._silence_logged:
                self.log(
                    "info",
                    f"frames again: frame {self.max_seq} after "
                    f"{now - self._silent_since:.1f} s of wall time without one",
                )
            self._frames_seen, self._silent_since, self._silence_logged = n, now, False
        elif self._last_check > 0.0 and now - self._last_check > self.self_stall_s:
            self._silent_since = now  # we stood still ourselves: not the frames' silence
        elif n and not self._silence_logged and now - self._silent_since > self.frame_silence_s:
            self._silence_logged = True
            self.log(
                "warning",
                f"no frame for {now - self._silent_since:.1f} s of wall time after frame "
                f"{self.max_seq} (answered up to {self.next_k - 1}): the frame source stopped, "
                "or a frame lost in transit holds every later one until it is sent again "
                "(reliable in-order delivery)",
            )

    # ------------------------------------------------------------------ sequencing
    def _run(self) -> None:
        frames, ests = self.frames, self.ests
        while True:
            k = self.next_k
            fr = frames.get(k)
            if fr is None:
                if not frames or self.max_seq <= k:
                    return
                # frame k never came but later ones did (lost upstream): skip to them
                first = min(frames)
                self.counts["missing_frames"] += first - k
                for j in [j for j in ests if j < first]:
                    del ests[j]
                self.next_k = k = first
                fr = frames[k]
            if self.sensorless:
                es = ests.pop(k, None)
                if es is None:
                    if self.tripped:
                        es = self.no_est  # tripped: no need to wait for the estimate
                    elif self._behind() and self._skip_to_newest_pair(k):
                        continue
                    elif self._sample_timeout(k):
                        late_ms = (self.max_seq - k) * self.ts * 1e3
                        self.trip_stale(
                            f"no position estimate for frame {k} while frames up to "
                            f"{self.max_seq} arrived ({late_ms:.1f} ms of sample time)"
                        )
                        es = self.no_est
                    else:
                        return
            else:
                es = self.no_est
            del frames[k]
            self._answer(k, fr, es)
            self.next_k = k + 1

    def _behind(self) -> bool:
        """The newest frame says the power stage has cut the PWM although our last duty
        asked for it: this controller fell behind (stalled) and is catching up."""
        newest = self.frames.get(self.max_seq)
        return (
            newest is not None and newest[FR_EN] < 0.5 and self.enables.get(self.next_k - 1, False)
        )

    def _skip_to_newest_pair(self, k: int) -> bool:
        """Catching up after a stall, as a drive's control task does: go on with the newest
        frame whose estimate is here (the queued ones in between would be answered too
        late to be applied); False if there is none newer than k."""
        j = max((j for j in self.ests if j > k and j in self.frames), default=-1)
        if j < 0:
            return False
        for i in [i for i in self.frames if i < j]:
            del self.frames[i]
        for i in [i for i in self.ests if i < j]:
            del self.ests[i]
        self.counts["skipped_frames"] += j - k
        # the skipped frames' duties were never sent: the PWM state they'd show is unknown
        self.enables[j - 2] = self.enables[j - 1] = self.enables.get(k - 1, False)
        self.next_k = j
        return True

    def _sample_timeout(self, k: int) -> bool:
        """The estimate of frame k is overdue by sample time: frames n_pos_timeout later
        are here, and it has been waited for at least min_wait_s of wall time (a process
        catching up with queued frames and estimates gets them in bursts that say nothing
        about time; the same at the start, and after a lost interval: wall clock only)."""
        now = time.monotonic()
        if self.wait_k != k:
            self.wait_k = k
            self.t_wait = now
        if (
            self.max_seq - k < self.n_pos_timeout
            or self.lost_run
            or not self.counts["estimates"]
            or now - self.t_wait < self.min_wait_s
        ):
            return False
        return not self._behind()  # we are the ones behind (stalled), not the observer

    def _lost(self, k: int, fr: np.ndarray) -> bool:
        """Frame k was made with PWM off although duty(k-2) asked for it on."""
        return self.enables.pop(k - 2, False) and fr.item(FR_EN) < 0.5

    def _answer(self, k: int, fr: np.ndarray, es: np.ndarray) -> None:
        cs = self.cs
        tripped = cs.item(CS_MODE) == MODE_FAULT
        if not tripped:
            if self._lost(k, fr):
                self._resync(k, es)
                tripped = cs[CS_MODE] == MODE_FAULT  # too many lost intervals: latched
            elif self.lost_run:
                # each lost frame re-decided flying vs. start-up (a braked rotor slows
                # below the handover speed during a long gap): say which one resumes
                how = (
                    "flying restart on the estimate"
                    if cs[CS_MODE] == MODE_CLOSED_LOOP
                    else "restarting through align / I-f"
                )
                self.log(
                    "info",
                    f"PWM back at frame {k} after {self.lost_run} lost "
                    f"period(s) from frame {self.lost_first}; {how}",
                )
                self.lost_run = 0
        n = self.w_ref_profile.shape[0]
        w_ref = (
            self.const_ref
            if self.const_ref is not None
            else self.w_ref_profile.item(min(max(k, 0), n - 1))
        )
        inj = self.id_inj.item(k) if 0 <= k < self.id_inj.shape[0] else 0.0
        out = self.out
        w_fb_prev = out.item(CO_W_FB)
        if self.split:
            host_reference_step(cs, self.cp, fr, es, w_ref, inj, out, self.ref)
        else:
            self._step(cs, self.cp, fr, es, w_ref, inj, out)
        if not tripped and cs.item(CS_MODE) == MODE_FAULT:
            code = int(cs[CS_FAULT])
            self.fault_detail = f"{trip_values(code, fr, es, self.cp, cs, w_fb_prev)} (frame {k})"
            self._log_fault(code)
        if self.recover_from >= 0 and out[CO_MODE] == MODE_CLOSED_LOOP and not self.lost_run:
            self.log(
                "info",
                f"closed loop again at frame {k}, {k - self.recover_from} "
                f"period(s) after the lost interval began",
            )
            self.recover_from = -1
        enables = self.enables
        enables[k] = out.item(CO_EN) > 0.5
        enables.pop(k - 5, None)  # only the last few are read (k - 2 at most back)
        if len(enables) > 8:  # older ones left by a jump in k
            for j in [j for j in enables if j < k - 4]:
                del enables[j]
        self.finished_k = k
        if len(self.spare) < 4:  # the frame is done with
            self.spare.append(fr)
        self.emit(k, out)

    def _resync(self, k: int, es: np.ndarray) -> None:
        """A lost interval: re-synchronise instead of counting it as loss of lock."""
        cs, cp, c = self.cs, self.cp, self.counts
        c["lost_frames"] += 1
        first = self.lost_run == 0
        self.lost_run += 1
        if first:
            self.lost_first = k
            if self.recover_from < 0:
                self.recover_from = k
            c["lost_intervals"] += 1
            win = round(self.resync_window_s / self.ts)
            self.resync_at = [j for j in self.resync_at if j > k - win] + [k]
            if len(self.resync_at) > self.max_resyncs:
                self.fault_detail = (
                    f"{len(self.resync_at)} lost intervals (PWM switched off by the power "
                    f"stage's watchdog) within {self.resync_window_s:g} s of sample time, "
                    f"limit {self.max_resyncs} (frame {k})"
                    if self.max_resyncs
                    else f"the power stage's watchdog switched the PWM off at frame {k}: no "
                    f"duty command from this controller for its wall-time limit (stopped or "
                    f"dead, not late)"
                )
                cs[CS_MODE] = MODE_FAULT
                cs[CS_FAULT] = FAULT_WATCHDOG
                self._log_fault(FAULT_WATCHDOG)
                return
        flying = (
            cs[CS_MODE] == MODE_CLOSED_LOOP
            and es[ES_VALID] != 0.0
            and math.isfinite(es[ES_W])
            and abs(es[ES_W]) >= cp[CP_HANDOVER] * cp[CP_P]
        )
        if flying:
            cs[CS_ID_I] = 0.0
            cs[CS_IQ_I] = 0.0
            cs[CS_INV_T] = 0.0
            c["flying_restarts"] += first
        else:
            controller_reset(cs)
            c["restarts"] += first
        if first:
            self.log(
                "warning",
                (
                    f"frame {k}: PWM was off although duty {k - 2} asked for it (the power "
                    f"stage's watchdog: this controller fell behind) -- interval lost; "
                    + (
                        "flying restart on the estimate"
                        if flying
                        else "restarting through align / I-f"
                    )
                ),
            )

    # ------------------------------------------------------------------ faults
    def _log_fault(self, code: int) -> None:
        self.counts["faults_latched"] += 1
        name = FAULT_NAMES.get(code, f"fault {code}")
        self.log("error", f"{name}: {self.fault_detail}; PWM off (latched)")

    def trip_stale(self, detail: str) -> None:
        """Latch "stale input": from the next step on the controller outputs PWM off."""
        self.cs[CS_MODE] = MODE_FAULT
        self.cs[CS_FAULT] = FAULT_STALE_INPUT
        self.counts["stale_trips"] += 1
        self.fault_detail = detail
        self._log_fault(FAULT_STALE_INPUT)

    def reset_fault(self) -> tuple[int, str]:
        """Explicit reset of a latched fault: (cleared code, its detail); the drive starts
        again (align, I-f, handover) from the next frame."""
        if not self.tripped:
            return 0, ""
        code = int(controller_clear_fault(self.cs))
        detail, self.fault_detail = self.fault_detail, ""
        self.rejected_run = 0
        self.wait_k = -1
        self.lost_run = 0
        self.recover_from = -1
        self.resync_at = []
        self.enables.clear()
        return code, detail
