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
    ID_DRIVE_PARAM,
    ID_DUTY_CMD,
    ID_HOST_HEARTBEAT,
    ID_HOST_REF,
    SEQ_BITS,
    FluxdriveProtocol,
    get_protocol,
)
from fluxdrive.drive.plant import FR_N, TR_N, plant_advance, plant_initial_frame

__all__ = ["DriveEmulator", "EmulatorStats"]

_SEQ_MOD = 1 << SEQ_BITS


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
    ) -> None:
        if mcu not in ("c", "pil"):
            raise ValueError(f"mcu must be 'c' or 'pil', not {mcu!r}")
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
        self._fw: Any = self._new_firmware()
        self.stage_temp_c = 35
        """The power stage's temperature the drive reads [degC] (the plant has no thermal
        model: fault injection sets it)."""
        self.sample_hook: Callable[[int, np.ndarray], None] | None = None
        """Fault injection: called with (k, a copy of frame k) before the core reads it;
        what it changes in the copy is what the drive's sensors report (the plant's state
        stays as it is)."""
        for name, value in (params or {}).items():
            status = self._fw.param_write(name, float(value))
            if status != "OK":
                raise ValueError(f"C drive core refused {name} = {value:g}: {status}")

    def _new_firmware(self) -> Any:
        """The drive's MCU (``mcu``): the C core with the SIL HAL, or the virtual board."""
        kw: dict[str, Any] = {"decimation": self.decimation, "classic": self.layout == "classic"}
        kw["cmd_timeout_s"] = self._cmd_timeout_s
        if self.mcu == "pil":  # the board image on the virtual board (fluxdrive.can.vboard)
            from fluxdrive.can.vboard import VirtualBoard

            return VirtualBoard(self.setup.mp, **kw)
        return FirmwareCore(self.setup.mp, status_period_s=self._status_period_s, **kw)

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
        if msg.arbitration_id == ID_HOST_HEARTBEAT:
            self.host_heard_s = time.monotonic()
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

    def _drain(self, timeout: float = 0.0) -> None:
        """Take everything already received; wait at most ``timeout`` for the first."""
        msg = self.bus.recv(timeout=timeout)
        while msg is not None:
            self._handle(msg)
            msg = self.bus.recv(timeout=0.0)

    # ------------------------------------------------------------------ periods

    def step(self) -> None:
        """One PWM period (see the module doc)."""
        k = self.k
        d = self.decimation
        fw = self._fw
        if self.record:
            self.rec_frames.append(self.frame.copy())
            self.rec_truth.append(self.truth.copy())
        self._drain(0.0)
        self._fw_feed(hold_refs=self.lockstep and k % d != 0)
        if k % d == 0 and k >= d and self.lockstep:
            want = (k - d) % _SEQ_MOD
            deadline = time.monotonic() + self.lockstep_wait_s
            while not fw.has_answer(want) and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0.0:
                    self.stats.lockstep_timeouts += 1
                    break
                self._drain(min(left, 0.05))
                self._fw_feed()
        if self.sample_hook is None:
            fw.set_sample(self.frame, self.time_us(), self.stage_temp_c)
        else:
            seen = self.frame.copy()
            self.sample_hook(k, seen)
            fw.set_sample(seen, self.time_us(), self.stage_temp_c)
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
        s = self.setup
        plant_advance(
            self.pst, s.mp, self.rng, duty, enabled, s.load_t, s.load_y, s.load_cfg,
            self.frame, self.truth,
        )  # fmt: skip
        self.k = k + 1
        self._sync_stats()

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
            try:
                self.bus.send(msg, timeout=self.send_timeout_s)
            except can.CanError:
                self.stats.tx_timeouts += 1

    def _sync_stats(self) -> None:
        """The C core's counters under the emulator's names."""
        c = self._fw.stats()
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
            if until_armed and self._fw.state()["armed"]:
                self.armed = True
                return

    def run(self, n_periods: int, realtime: bool = False) -> None:
        """Run ``n_periods`` periods (or until :meth:`stop`). ``realtime`` paces the
        periods to wall time (free-running MCU)."""
        t0 = time.perf_counter()
        for i in range(n_periods):
            if self._stop.is_set():
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
