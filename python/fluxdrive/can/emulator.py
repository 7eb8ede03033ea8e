"""Drive emulator: the project's plant, the C drive core and a python-can bus.

:class:`DriveEmulator` is one drive on a python-can bus. Its MCU is the C drive firmware
(``firmware/``, the only MCU the project has): by default (``mcu="c"``) through
:class:`fluxdrive.can.firmware.FirmwareCore` (the core plus its software-in-the-loop HAL),
with ``mcu="pil"`` the board image on the virtual board (:mod:`fluxdrive.can.vboard`, the
same interface, its own timer model with compare preload);
its power stage and motor are the project's plant (``DriveSetup`` + ``plant_advance``, the
same compiled kernels the in-process runner and the sim node use). Per PWM period k:

* the plant's frame k goes into the core as raw ADC counts, capture ticks and encoder
  counts; the frames received from the bus go into its CAN queue (parameter requests are
  served between interrupts, as a firmware's background loop would);
* the core's period interrupt runs: it sends the sample(s), STATUS, FAULT frames, takes
  the host's DUTY_CMD (host mode) or HOST_REF (split mode, its current loop), supervises
  its protections, and writes the PWM;
* what it sent goes onto the bus; the plant simulates [t_k, t_(k+1)] with the PWM the
  timer holds over that period -- the compare values the *previous* interrupt wrote
  (a real timer's preload: a duty written at t_k applies from t_(k+1); an enable cleared
  at t_k opens the gates at once; firmware/include/fd_hal.h) -- and samples frame k+1.

What the MCU does (arming, watchdogs, protections, faults, parameters, sample layouts and
decimation, split mode) is the C core's and documented there and in docs/firmware.md.

In *lockstep* mode (default) the emulator waits, at each sample boundary k >= D, up to
``lockstep_wait_s`` of wall time for the host's answer to sample k-D before running the
interrupt, so runs are deterministic and reproduce the in-process runner up to the
protocol's quantisation, and the drive's microsecond clock is its own time (k periods);
free-running (``lockstep=False``) it takes whatever has arrived and its clock is wall time
(a real MCU).

``inject`` (a :class:`fluxdrive.can.faultcases.Injection`, or a list run one after the
other) injects a protection's condition from a period on -- sensors, HAL inputs, host frames
-- the same way on either MCU, holds it ``INJECT_HOLD`` periods after the PWM went off, then
removes it; the next one starts once the host has reset and re-armed the drive and PWM has
run ``INJECT_SETTLE`` periods. Each reaction is recorded (``EmulatorStats.injections``); the
run ends ``INJECT_HOLD`` periods after the last one was removed.
``sample_hook`` changes what the drive's sensors report (fault injection); ``status_period_s``
is the core's STATUS period. The core boots with its own defaults (the parameters a host
writes before arming, as on a real drive); ``params`` writes DRIVE_PARAMs before the first
period (a drive whose parameters are stored). No ROS imports. Sends always use a timeout
(python-can's ``virtual`` bus blocks forever on a full receive queue otherwise).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from fluxdrive.can.firmware import FirmwareCore
from fluxdrive.can.protocol import (
    CLASSIC_SAMPLE_IDS,
    ID_ARM_MODE,
    ID_DRIVE_PARAM,
    ID_DUTY_CMD,
    ID_FAULT,
    ID_HOST_HEARTBEAT,
    ID_HOST_REF,
    ID_SAMPLE_FD,
    ID_STATUS,
    SEQ_BITS,
    FluxdriveProtocol,
    get_protocol,
)
from fluxdrive.core.protocol_constants import MODE_CALIBRATE_ADC
from fluxdrive.drive.plant import FR_N, TR_N, plant_advance, plant_initial_frame

__all__ = ["DriveEmulator", "EmulatorStats"]

_SEQ_MOD = 1 << SEQ_BITS
INJECT_HOLD = 20
"""Periods an injected condition is held after the PWM went off (the latch must hold)."""
INJECT_SETTLE = 20
"""Periods of PWM after a re-arming before the next injection."""


@dataclass
class EmulatorStats:
    """Counters of the drive: the C core's (``fd_stats_t``) and the emulator's own
    (lockstep waits that timed out, sends that timed out, fault codes raised)."""

    periods: int = 0
    samples_sent: int = 0
    duty_rx: int = 0
    duty_applied: int = 0
    duty_late: int = 0  # a DUTY_CMD answering an older sample than the one needed
    stale_periods: int = 0
    lockstep_timeouts: int = 0
    arm_rx: int = 0
    bad_rx: int = 0
    filtered_rx: int = 0  # frames the MCU's acceptance filter kept out (not the host's)
    tx_timeouts: int = 0
    layout_mismatch: int = 0
    disarm_rx: int = 0
    faults: int = 0
    fault_codes: list[int] = field(default_factory=list)
    ref_rx: int = 0  # split mode: HOST_REF received
    refs_applied: int = 0  # HOST_REF taken by the current loop
    param_rx: int = 0  # DRIVE_PARAM requests answered
    # datagrams on a software bus's group and port that are no CAN message (another
    # program's UDP traffic on that port): dropped, as a CAN controller never hands its MCU
    # a frame it could not receive
    foreign_datagrams: int = 0
    # fault injection (``inject``), per injection: the case, the period it started, whether
    # PWM ran in the period before, the first period from then on that ran with PWM off,
    # periods with PWM on after that while it was held (a latch: none), what was injected,
    # the reaction bound [periods], the FAULT frames sent meanwhile ([k, code, detail])
    injections: list[dict[str, Any]] = field(default_factory=list)
    injected_frames: int = 0  # host frames an injection dropped or changed

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class DriveEmulator:
    """The plant and the C drive core on a python-can bus (see module doc).

    ``setup`` is a :class:`fluxdrive.drive.sim.DriveSetup` (plant parameters, load profile,
    seed). ``bus`` is any python-can bus (usually ``interface="virtual"`` in-process).
    ``record`` keeps the true state per period (``truth``) and the frames sent, for tests,
    and times the host's answers (``answer_latency_s``); ``time_answers`` only times them.
    """

    def __init__(
        self,
        setup: Any,
        bus: can.BusABC,
        *,
        lockstep: bool = True,
        lockstep_wait_s: float = 0.5,
        cmd_timeout_s: float = 1e-3,
        params: dict[str, float] | None = None,
        status_period_s: float = 0.1,
        send_timeout_s: float = 0.5,
        record: bool = False,
        time_answers: bool = False,
        layout: str = "fd",
        decimation: int | None = None,
        protocol: FluxdriveProtocol | None = None,
        mcu: str = "c",
        inject: Any = None,
        require_calibration: bool = False,
        bootstrap: bool = False,
        flash_image: bytes | None = None,
    ) -> None:
        if mcu not in ("c", "pil"):
            raise ValueError(f"mcu must be 'c' or 'pil', not {mcu!r}")
        if flash_image is not None and mcu != "pil":
            raise ValueError("a flash image is the virtual board's (mcu='pil')")
        self.flash_image = flash_image
        """mcu="pil": the flash the board boots from (VirtualBoard.flash_image of an
        earlier run: its stored parameters); None: erased."""
        self.mcu = mcu
        self.setup = setup
        self.bus = bus
        self.proto = protocol or get_protocol()
        if layout not in ("fd", "classic"):
            raise ValueError(f"layout must be 'fd' or 'classic', not {layout!r}")
        self.layout = layout
        d = self.proto.default_decimation(layout) if decimation is None else int(decimation)
        if not 1 <= d <= 255:
            raise ValueError(f"decimation must be in 1..255, not {d}")
        self.decimation = d
        """PWM periods per sample (either layout)."""
        self.lockstep = lockstep
        self.lockstep_wait_s = lockstep_wait_s
        self.send_timeout_s = send_timeout_s
        self._init_plant(setup)
        self._init_records(record, time_answers)
        self._warm_plant()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fw_rx: collections.deque[can.Message] = collections.deque()
        # the CAN controller's acceptance filter: only what the host sends reaches the MCU
        self._rx_ids = frozenset(
            m.frame_id for m in self.proto.db.messages if "BENCH_PC" in (m.senders or ())
        )
        self._t0_wall = time.monotonic()
        self._cmd_timeout_s = cmd_timeout_s
        self._status_period_s = status_period_s
        self.require_calibration = require_calibration
        """The C core refuses to arm before an offset calibration (FAULT NOT_CALIBRATED),
        as the board image does; the in-process loops' hosts calibrate either way."""
        self.bootstrap = bootstrap
        """The C core charges the bootstrap capacitors after arming (its default periods,
        low sides on, as the board image does) before the first switching period."""
        self.calibration_periods = 0  # periods run calibrating while served (pre-run)
        self._stats0: dict[str, int] = {}  # the core's counters at the run's start
        self._init_injections(inject)
        self._fw: Any = self._new_firmware()
        self.stage_temp_c = 35
        """The power stage's temperature the drive reads [degC] (the plant has no thermal
        model: fault injection sets it)."""
        self.sample_hook: Callable[[int, np.ndarray], None] | None = None
        """Fault injection: called with (k, a copy of frame k) before the core reads it;
        what it changes in the copy is what the drive's sensors report (the plant's state
        stays as it is)."""
        self._store_params(params or {})
        if self.inject is not None and self.inject.case.before_arming:  # for the arming
            self._start_injection(self.inject)

    def _init_records(self, record: bool, time_answers: bool) -> None:
        """What a run keeps besides the bus: the frames (record) and the answers' timing."""
        self.record = record
        self.rec_frames: list[np.ndarray] = []
        self.rec_truth: list[np.ndarray] = []
        # record=True or time_answers=True: wall time (time.time) each sample went out, by
        # wire seq, and the host's answer latency [s] (the answer's bus timestamp minus its
        # sample's send time), for benchmarks
        self._time_answers = bool(record or time_answers)
        self._sent_wall: dict[int, float] = {}
        self.answer_latency_s: list[float] = []
        # the answers' sequence signals: DUTY_CMD.cmd_seq, HOST_REF.ref_seq
        self._answer_seq = {ID_DUTY_CMD: "cmd_seq", ID_HOST_REF: "ref_seq"}
        self.host_heard_s: float | None = None  # monotonic time of the last HOST_HEARTBEAT
        self.schedule_clock = False
        """Free-running: the drive's clock is its periods (k periods, as in lockstep), not
        the wall clock -- for an emulator paced to the wall clock, whose process the PC can
        stall: it catches up, and an MCU's timer never stalls (the host's lateness stays
        the host's)."""

    def _init_plant(self, setup: Any) -> None:
        """The plant at its initial frame (k = 0), the drive's state and counters."""
        self.ts = float(setup.ts)
        self.pst, self.rng = setup.new_plant()
        self.frame = np.zeros(FR_N)
        self.truth = np.zeros(TR_N)
        plant_initial_frame(self.pst, setup.mp, self.rng, self.frame, self.truth)
        self.k = 0  # index of the frame held in self.frame
        self.stats = EmulatorStats()
        self.armed = self.pwm_enabled = self.fault_latched = False
        self.fault_code = self.mode = 0
        self.duty = np.full(3, 0.5)  # over the period last simulated

    def _store_params(self, params: dict[str, float]) -> None:
        """DRIVE_PARAMs written before the first period (a drive whose parameters are
        stored)."""
        for name, value in params.items():
            status = self._fw.param_write(name, float(value))
            if status != "OK":
                raise ValueError(f"C drive core refused {name} = {value:g}: {status}")

    def _init_injections(self, inject: Any) -> None:
        self.injections: list[Any] = (
            [] if inject is None else list(inject) if isinstance(inject, list) else [inject]
        )
        """The fault injections (fluxdrive.can.faultcases.Injection), in order."""
        self.inject = self.injections[0] if self.injections else None
        """The injection in force or next (None: none left)."""
        self._pwm_prev = False
        self._pwm_run = 0  # periods PWM has run without a break
        self._heartbeat_k = -1  # the period of the last HOST_HEARTBEAT or arming
        self._inject_done_k: int | None = None
        self._answers_lost_k = -1  # answers to samples before this period were lost
        first = self.inject
        if first is not None and first.case.before_arming:
            if first.k_at != 0 or len(self.injections) > 1:
                raise ValueError(f"{first.case.name} is injected alone, before arming (at 0 s)")

    def _new_firmware(self) -> Any:
        """The drive's MCU (``mcu``): the C core with the SIL HAL, or the virtual board."""
        kw: dict[str, Any] = {"decimation": self.decimation, "classic": self.layout == "classic"}
        kw["cmd_timeout_s"] = self._cmd_timeout_s
        if self.mcu == "pil":  # the board image on the virtual board (fluxdrive.can.vboard)
            from fluxdrive.can.vboard import VirtualBoard

            return VirtualBoard(self.setup.mp, flash_image=self.flash_image, **kw)
        kw["require_calibration"] = self.require_calibration
        if self.inject is not None and self.inject.case.before_arming:
            kw["require_calibration"] = self.inject.case.name == "not_calibrated"
        if self.bootstrap:
            kw["bootstrap_periods"] = None  # the core's default
        return FirmwareCore(self.setup.mp, status_period_s=self._status_period_s, **kw)

    @property
    def requires_calibration(self) -> bool:
        """The drive refuses to arm before an offset calibration: the board image always,
        the C core with ``require_calibration``."""
        return self.require_calibration or self.mcu == "pil"

    @property
    def core(self) -> Any:
        """The drive's MCU (tests inject conditions through its HAL)."""
        return self._fw

    def _warm_plant(self) -> None:
        """Compile (or load) the plant kernel now, not in the first periods (a host waiting
        for samples would see a stale link); on copies."""
        s = self.setup
        plant_advance(
            self.pst.copy(), s.mp, self.rng.copy(), self.duty.copy(), False, s.load_t,
            s.load_y, s.load_cfg, self.frame.copy(), self.truth.copy(),
        )  # fmt: skip

    # ------------------------------------------------------------------ bus I/O

    def _handle(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_extended_id:
            return
        if msg.arbitration_id not in self._rx_ids:  # a flood of other IDs never queues
            self.stats.filtered_rx += 1
            return
        inj = self.inject
        if inj is not None and inj.active:
            changed = inj.host_frame(msg, self.proto)
            if changed is not msg:
                self.stats.injected_frames += 1
            if changed is None:
                return
            msg = changed
        if msg.arbitration_id == ID_HOST_HEARTBEAT:
            self.host_heard_s = time.monotonic()
            self._heartbeat_k = self.k
        elif msg.arbitration_id == ID_ARM_MODE and self._arms(msg):
            self._heartbeat_k = self.k  # the drive supervises the heartbeat from arming
        seq_signal = self._answer_seq.get(msg.arbitration_id)
        if self._time_answers and seq_signal is not None:
            try:
                seq = int(self.proto.decode(msg.arbitration_id, bytes(msg.data))[seq_signal])
            except Exception:  # noqa: BLE001 - a bad frame: the core counts it
                seq = -1
            t = self._sent_wall.pop(seq, None)
            if t is not None and msg.timestamp > 0.0:
                self.answer_latency_s.append(msg.timestamp - t)
        self._fw_rx.append(msg)

    def _arms(self, msg: can.Message) -> bool:
        """An ARM_MODE that arms the drive (the start of its host supervision)."""
        try:
            return bool(self.proto.decode(ID_ARM_MODE, bytes(msg.data))["arm"])
        except Exception:  # noqa: BLE001 - a bad frame: the core counts it
            return False

    def _drain(self, timeout: float = 0.0) -> None:
        """Take everything already received; wait at most ``timeout`` for the first.  A
        datagram the bus cannot unpack is counted (``foreign_datagrams``) and dropped, as the
        bridge does (``CanBridge._recv``): the drive runs on."""
        while True:
            try:
                msg = self.bus.recv(timeout=timeout)
            except can.CanOperationError as exc:
                if "could not unpack" not in str(exc):
                    raise
                self.stats.foreign_datagrams += 1
                timeout = 0.0
                continue
            if msg is None:
                return
            self._handle(msg)
            timeout = 0.0

    # ------------------------------------------------------------------ periods

    def step(self) -> None:
        """One PWM period (see the module doc)."""
        k = self.k
        d = self.decimation
        fw = self._fw
        if self.record:
            self.rec_frames.append(self.frame.copy())
            self.rec_truth.append(self.truth.copy())
        inj = self.inject
        if inj is not None and not inj.active and self._ready(inj):
            self._start_injection(inj)
        self._drain(0.0)
        self._fw_feed(hold_refs=self.lockstep and k % d != 0)
        # lockstep: the host's answer to sample k-D, waited for (not while the drive
        # calibrates its offsets: disarmed, it is not answered)
        calibrating = self.mode == MODE_CALIBRATE_ADC
        waits = (
            inj is None or not inj.active or inj.host_answers
        ) and k - d >= self._answers_lost_k
        if k % d == 0 and k >= d and self.lockstep and waits and not calibrating:
            want = (k - d) % _SEQ_MOD
            deadline = time.monotonic() + self.lockstep_wait_s
            while not fw.has_answer(want) and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0.0:
                    self.stats.lockstep_timeouts += 1
                    break
                self._drain(min(left, 0.05))
                self._fw_feed()
        if self.sample_hook is None and (inj is None or not inj.active):
            fw.set_sample(self.frame, self.time_us(), self.stage_temp_c)
        else:
            seen = self.frame.copy()
            temp_c = self.stage_temp_c
            if self.sample_hook is not None:
                self.sample_hook(k, seen)
            if inj is not None and inj.active:
                inj.sensors(seen)
                temp_c = inj.temp_c if inj.temp_c is not None else temp_c
            fw.set_sample(seen, self.time_us(), temp_c)
        fw.period()
        if self._time_answers and k % d == 0:
            self._sent_wall[k % _SEQ_MOD] = time.time()
            if len(self._sent_wall) > 256:
                del self._sent_wall[next(iter(self._sent_wall))]
        self._fw_send()
        duty, enabled = fw.pwm()  # the timer's registers over [t_k, t_(k+1)]
        st = fw.state()
        self.armed = bool(st["armed"])
        self.pwm_enabled = bool(st["pwm_enabled"])
        self.fault_latched = bool(st["fault_latched"])
        self.fault_code = int(st["fault_code"])
        self.mode = int(st["mode"])
        self.duty = duty
        if inj is not None and inj.active:
            self._follow_injection(inj, bool(enabled))
        self._pwm_prev = bool(enabled)
        self._pwm_run = self._pwm_run + 1 if enabled else 0
        s = self.setup
        plant_advance(
            self.pst, s.mp, self.rng, duty, enabled, s.load_t, s.load_y, s.load_cfg,
            self.frame, self.truth,
        )  # fmt: skip
        self.k = k + 1
        self._sync_stats()

    def _ready(self, inj: Any) -> bool:
        """The next injection may start: the first at its period, each later one once PWM
        has run INJECT_SETTLE periods again (the host reset and re-armed the drive)."""
        if inj is self.injections[0]:
            return self.k >= inj.k_at
        return self._pwm_run >= INJECT_SETTLE

    def _follow_injection(self, inj: Any, enabled: bool) -> None:
        """Per period while `inj` is in force: its reaction recorded; INJECT_HOLD periods
        after the PWM went off the condition is removed and the next one is up."""
        rec = self.stats.injections[-1]
        if not enabled and rec["pwm_off_k"] < 0:
            rec["pwm_off_k"] = self.k
        elif enabled and rec["pwm_off_k"] >= 0:
            rec["pwm_on_after_off"] += 1
        if rec["pwm_off_k"] >= 0 and self.k >= rec["pwm_off_k"] + INJECT_HOLD:
            if not inj.host_answers:  # the answers to the samples until now are lost
                self._answers_lost_k = self.k
            inj.stop(self._fw)
            i = self.injections.index(inj) + 1
            self.inject = self.injections[i] if i < len(self.injections) else None
            if self.inject is None:
                self._inject_done_k = self.k

    @property
    def injections_done(self) -> bool:
        """Every injection was made and removed, and INJECT_HOLD periods have passed."""
        done = self._inject_done_k
        return done is not None and self.k >= done + INJECT_HOLD

    def _start_injection(self, inj: Any) -> None:
        """The injection's start at its period: limits read, HAL inputs set, a stray frame
        queued (fluxdrive.can.faultcases)."""
        inj.start(self._fw, self.ts, self.decimation)
        self.stats.injections.append(
            {"case": inj.case.name, "inject_k": self.k, "pwm_on_before": self._pwm_prev,
             "pwm_off_k": -1, "pwm_on_after_off": 0, "inject_level": inj.level,
             "inject_bound": inj.bound, "fault_frames": [], "heartbeat_k": self._heartbeat_k}
        )  # fmt: skip
        stray = inj.stray_frame(self.proto, bool(self._fw.state()["split"]), self.decimation)
        if stray is not None:
            self._fw_rx.append(stray)

    def time_us(self) -> int:
        """The drive's free-running microsecond clock: free-running, wall time since
        construction; in lockstep the drive's own time, k periods (the drive waits for the
        host, so its host supervision -- heartbeat timeout -- counts drive time too)."""
        if self.lockstep or self.schedule_clock:
            return int(round(self.k * self.ts * 1e6))
        return int((time.monotonic() - self._t0_wall) * 1e6)

    def _fw_feed(self, hold_refs: bool = False) -> None:
        """Received frames into the C core's RX queue (what does not fit waits).
        ``hold_refs``: HOST_REFs wait for the next sample boundary (lockstep split mode takes
        the answer to sample k-D at boundary k, like the in-process split loop; free-running,
        the core takes the newest at any period boundary)."""
        fw = self._fw
        held: collections.deque[can.Message] = collections.deque()
        while self._fw_rx:
            msg = self._fw_rx[0]
            if msg.arbitration_id == ID_DRIVE_PARAM:
                # parameter requests are served between interrupts (a firmware's background
                # loop), so a host waiting for the ACK never stalls a lockstep period
                fw.handle_now(self._fw_rx.popleft())
                self._fw_send()
                self._sync_stats()
                continue
            if hold_refs and msg.arbitration_id == ID_HOST_REF:
                held.append(self._fw_rx.popleft())
                continue
            if not fw.push(msg):
                break
            self._fw_rx.popleft()
        self._fw_rx.extendleft(reversed(held))

    def _fw_send(self) -> None:
        """What the C core sent, onto the bus."""
        for msg in self._fw.pop_tx():
            inj = self.inject
            if inj is not None and inj.active and msg.arbitration_id == ID_FAULT:
                f = self.proto.decode(ID_FAULT, bytes(msg.data))
                frames = self.stats.injections[-1]["fault_frames"]
                if len(frames) < 16:
                    frames.append([self.k, int(f["fault_code"]), int(f["fault_detail"])])
            try:
                self.bus.send(msg, timeout=self.send_timeout_s)
            except can.CanError:
                self.stats.tx_timeouts += 1

    def _sync_stats(self) -> None:
        """The C core's counters under the emulator's names, from the run's first period
        (an offset calibration before it apart: :attr:`calibration_periods`)."""
        c = {k: v - self._stats0.get(k, 0) for k, v in self._fw.stats().items()}
        st = self.stats
        st.periods = c["periods"]
        st.samples_sent = c["samples_sent"]
        st.duty_rx = c["duty_rx"]
        st.ref_rx = c["ref_rx"]
        st.refs_applied = c["refs_applied"]
        st.param_rx = c["param_rx"]
        st.duty_applied = c["duty_applied"]
        st.duty_late = c["duty_late"]
        st.stale_periods = c["stale_periods"]
        st.arm_rx = c["arm_rx"]
        st.bad_rx = c["bad_rx"]
        st.layout_mismatch = c["layout_mismatch"]
        st.disarm_rx = c["disarm_rx"]
        if c["faults"] > st.faults:
            st.fault_codes.append(self.fault_code)
        st.faults = c["faults"]

    # ------------------------------------------------------------------ running

    def serve(
        self, until: threading.Event, poll_s: float = 0.01, until_armed: bool = False
    ) -> None:
        """Answer the bus (ARM_MODE, DRIVE_PARAM, ...) without running periods, until
        `until` is set (or, with `until_armed`, the host armed the drive): the drive before
        its first period (e.g. configured by the host)."""
        while not until.is_set() and not self._stop.is_set():
            self._drain(poll_s)
            while self._fw_rx:  # the core answers between interrupts
                self._fw.handle_now(self._fw_rx.popleft())
            self._fw_send()
            self._sync_stats()
            if self._fw.state()["mode"] == MODE_CALIBRATE_ADC:
                self._calibrate_at_standstill()
            st = self._fw.state()
            if until_armed and st["armed"]:
                self.armed = True
                return
            if until_armed and st["fault_latched"]:  # the arming refused with a fault
                self.fault_latched = True
                return

    def _calibrate_at_standstill(self) -> None:
        """The drive's offset calibration before the run (ARM_MODE mode CALIBRATE_ADC while
        served): its periods run, PWM off, on the plant at standstill -- copies of the
        plant's state and noise stream advanced with the gates open, so the run starts as
        it would have -- until the drive's STATUS after the calibration has gone out; what
        the drive sends goes onto the bus but its samples (the bench's sample stream starts
        with the run). Lockstep: the core's period counter then starts again at 0 (the
        run's sample index counts from the arming; ``restart_period_index``)."""
        fw, s = self._fw, self.setup
        pst, rng = self.pst.copy(), self.rng.copy()
        frame, truth = self.frame.copy(), self.truth.copy()
        gates_open = np.full(3, 0.5)
        samples = {ID_SAMPLE_FD, *CLASSIC_SAMPLE_IDS}
        status_after = False
        while not status_after and not self._stop.is_set():
            calibrating = fw.state()["mode"] == MODE_CALIBRATE_ADC
            self._drain(0.0)
            while self._fw_rx:  # the request's repeats, parameter reads: between periods
                fw.handle_now(self._fw_rx.popleft())
            fw.set_sample(frame, self.time_us(), self.stage_temp_c)
            fw.period()
            self.calibration_periods += 1
            for msg in fw.pop_tx():
                if msg.arbitration_id in samples:
                    continue
                status_after = status_after or (msg.arbitration_id == ID_STATUS and not calibrating)
                try:
                    self.bus.send(msg, timeout=self.send_timeout_s)
                except can.CanError:
                    self.stats.tx_timeouts += 1
            plant_advance(
                pst, s.mp, rng, gates_open, False, s.load_t, s.load_y, s.load_cfg, frame, truth
            )
        if self.lockstep:
            fw.restart_period_index()
        self._stats0 = fw.stats()  # the run's counters start here (EmulatorStats)
        self._sync_stats()

    def run(self, n_periods: int, realtime: bool = False) -> None:
        """Run ``n_periods`` periods (or until :meth:`stop`). ``realtime`` paces the
        periods to wall time (free-running MCU)."""
        t0 = time.perf_counter()
        for i in range(n_periods):
            if self._stop.is_set() or self.injections_done:
                break
            if realtime:
                lag = i * self.ts - (time.perf_counter() - t0)
                if lag > 0:
                    time.sleep(lag)
            self.step()

    def start(self, n_periods: int, realtime: bool = False) -> threading.Thread:
        """Run in a background thread; returns it."""
        self._stop.clear()
        self._thread = threading.Thread(
            target=self.run, args=(n_periods, realtime), name="drive-emulator", daemon=True
        )
        self._thread.start()
        return self._thread

    def stop(self, join_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(join_s)

    def recorded(self) -> tuple[np.ndarray, np.ndarray]:
        """(frames, truth) recorded so far (``record=True``)."""
        if not self.rec_frames:
            return np.empty((0, FR_N)), np.empty((0, TR_N))
        return np.vstack(self.rec_frames), np.vstack(self.rec_truth)
