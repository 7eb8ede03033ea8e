"""Drive emulator: the project's plant kernels behind the CAN protocol, acting as the MCU.

:class:`DriveEmulator` owns a plant (``DriveSetup`` + ``plant_advance``, the same compiled
kernels the in-process runner and the sim node use) and a python-can bus. Per PWM period
it does what the drive's microcontroller does (docs/engine.md timing convention, DBC comments):

* sends SAMPLE_FD(k): currents at t_k, line voltages / duties averaged over [t_(k-1), t_k]
  (with a decimation factor D > 1: every D-th period, averages over [t_(k-D), t_k], see
  below);
* the DUTY_CMD answering sample k (``cmd_seq = k``) is applied over [t_(k+1), t_(k+2)]:
  before simulating period k (which yields frame k+1) the emulator needs the duty of frame
  k-1. In *lockstep* mode it waits for it (up to ``lockstep_wait_s`` of wall time), so runs
  are deterministic and reproduce the in-process runner up to the protocol's quantisation;
  in free-running mode it takes whatever has arrived (a real MCU);
* a missing command holds the previous duties (``cmd_stale``); the duty-command watchdog
  (``ARM_MODE.cmd_timeout``, default 1 ms of *sim* time) disables PWM and latches
  CMD_TIMEOUT while PWM is enabled;
* ARM_MODE: arm=1 with key 0xA5 arms, anything else disarms (PWM off at once);
  reset_fault (rising edge) clears a latched fault; DUTY_CMD.cmd_enable switches PWM on
  only while armed with no fault latched;
* FAULT on every new fault (and at 10 Hz sim time while latched), STATUS at 10 Hz sim time;
  over-current trip on the sampled currents.

Sample layouts (``layout``) and the decimation factor D (``decimation``), both fixed at
construction like an MCU's firmware build (an ARM_MODE asking for another layout or D is
counted in ``layout_mismatch``; STATUS reports both so the host can check):

* ``"fd"``: one SAMPLE_FD (64 bytes, CAN FD with BRS) every D-th PWM period (default the
  DBC's FdDecimation = 1: every period; a real 1/5 Mbit/s bus needs D >= 4);
* ``"classic"``: the four 8-byte frames SAMPLE_C_CUR/VLT/DUTY/AUX every D-th period
  (default the DBC's ClassicDecimation = 8).

Decimation works the same in both layouts (one implementation): the sample of period
k = j*D (k = 0 included) carries currents, vdc and encoder at t_k, line voltages and
duties averaged over the D periods (t_(k-D), t_k], pwm_enabled only if on in all of them
(:func:`fluxdrive.can.protocol.decimate_frames` offline). The control loop runs at the
decimated rate: the DUTY_CMD answering sample k (cmd_seq = its seq) is held over
[t_(k+D), t_(k+2D)], i.e. the D = 1 timing with Ts -> D*Ts.

Split mode (ARM_MODE.control_split = 1): the MCU closes the dq current loop every PWM period
with the engine's own drive-side kernels (``split_drive_take_reference`` /
``split_drive_step`` in fluxdrive.drive.control) on the newest HOST_REF (lockstep: the one
answering sample k-D, taken at sample boundary k; free-running: whatever arrived last, at
each period boundary); the duty computed from frame k is applied over [t_(k+1), t_(k+2)].
No HOST_REF for REF_TIMEOUT_S while PWM is on: PWM off, WATCHDOG latched, FAULT frame.
DRIVE_PARAM writes/reads the drive-side parameters (``DRIVE_PARAM_FIELDS``, ranges
``DRIVE_PARAM_RANGES``) and answers each with a DRIVE_PARAM_ACK.

MCU logic (``mcu``): ``"python"`` (default) runs the logic above in this module; ``"pil"``
runs the board image that would be flashed on the virtual board (fluxdrive.can.vboard, the
same interface as the C core below, its PWM through the timer model's compare preload);
``"c"`` runs
the C drive firmware (``firmware/``, through :class:`fluxdrive.can.firmware.FirmwareCore`)
as the MCU: per period the plant's frame goes in as raw ADC/capture counts, the received
frames into its CAN queue, its period interrupt runs, and its PWM duties/enable drive
``plant_advance``; what it sends goes onto the bus. The Python logic stays the reference
the C core is tested against (tests/test_firmware.py).

No ROS imports. Sends always use a timeout (python-can's ``virtual`` bus blocks forever on
a full receive queue otherwise).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from fluxdrive.can.firmware import FirmwareCore
from fluxdrive.can.protocol import (
    ARM_KEY,
    FRAME_FLAG_ADC_CLIP,
    ID_ARM_MODE,
    ID_DRIVE_PARAM,
    ID_DRIVE_PARAM_ACK,
    ID_DUTY_CMD,
    ID_FAULT,
    ID_HOST_HEARTBEAT,
    ID_HOST_REF,
    ID_SAMPLE_FD,
    ID_STATUS,
    PROTOCOL_VERSION,
    SEQ_BITS,
    FluxdriveProtocol,
    get_protocol,
)
from fluxdrive.core.protocol_constants import (
    FAULT_HOST_HEARTBEAT_LOST,
    FAULT_NONE,
    FAULT_OVERCURRENT,
    FAULT_WATCHDOG,
    MODE_IDLE,
    MODE_RUN,
    ST_ARMED,
    ST_FAULT,
    ST_IDLE,
    ST_RUNNING,
)
from fluxdrive.drive.control import (
    CO_DA,
    CO_DC,
    CO_EN,
    CO_N,
    CP_REF_TIMEOUT,
    CS_FAULT,
    CS_MODE,
    CS_N,
    DR_AGE,
    DR_N,
    DRIVE_PARAM_FIELDS,
    DRIVE_PARAM_RANGES,
    DRIVE_PARAMS_STOPPED,
    MODE_FAULT,
    RF_EN,
    RF_ID_REF,
    RF_IQ_REF,
    RF_MODE,
    RF_N,
    RF_TH,
    RF_W,
    drive_param_values,
    split_drive_reset,
    split_drive_step,
    split_drive_take_reference,
)
from fluxdrive.drive.plant import (
    FR_DA,
    FR_DB,
    FR_DC,
    FR_EN,
    FR_ENC,
    FR_FLAGS,
    FR_IA,
    FR_IB,
    FR_IC,
    FR_N,
    FR_SEQ,
    FR_VAB,
    FR_VBC,
    FR_VCA,
    FR_VDC,
    TR_N,
    plant_advance,
    plant_initial_frame,
)

# the frame row's blocks (FR_*: phase currents, line voltages, duties)
_CURRENTS = slice(FR_IA, FR_IC + 1)
_V_LL = slice(FR_VAB, FR_VCA + 1)
_DUTIES = slice(FR_DA, FR_DC + 1)

__all__ = [
    "DriveEmulator",
    "EmulatorStats",
]

_SEQ_MOD = 1 << SEQ_BITS


@dataclass
class EmulatorStats:
    """Counters of the emulated MCU."""

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
    """The emulated drive MCU on a python-can bus (see module doc).

    ``setup`` is a :class:`fluxdrive.drive.sim.DriveSetup` (plant parameters, load profile,
    seed). ``bus`` is any python-can bus (usually ``interface="virtual"`` in-process).
    ``record`` keeps the true state per period (``truth``) and the frames sent, for tests.
    """

    def __init__(
        self,
        setup: Any,
        bus: can.BusABC,
        *,
        lockstep: bool = True,
        lockstep_wait_s: float = 0.5,
        cmd_timeout_s: float = 1e-3,
        overcurrent_a: float | None = None,
        heartbeat_timeout_s: float | None = None,
        send_timeout_s: float = 0.5,
        record: bool = False,
        layout: str = "fd",
        decimation: int | None = None,
        protocol: FluxdriveProtocol | None = None,
        mcu: str = "python",
    ) -> None:
        if mcu not in ("python", "c", "pil"):
            raise ValueError(f"mcu must be 'python', 'c' or 'pil', not {mcu!r}")
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
        self.cmd_timeout_s = cmd_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.send_timeout_s = send_timeout_s
        self.ts = float(setup.ts)
        card = setup.card
        self.overcurrent_a = (
            overcurrent_a if overcurrent_a is not None else 2.0 * card.rated_current_a
        )
        self._init_plant()
        self._init_mcu_state()
        self._init_recording(record)
        self._init_messages()
        self._init_window()
        self._init_split()
        self._warm_kernels()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fw: Any = None
        self._fw_rx: collections.deque[can.Message] = collections.deque()
        # the CAN controller's acceptance filter: only what the host sends reaches the MCU
        self._rx_ids = frozenset(
            m.frame_id for m in self.proto.db.messages if "BENCH_PC" in (m.senders or ())
        )
        self._t0_wall = time.monotonic()
        if mcu in ("c", "pil"):
            self._fw = self._new_firmware()

    def _init_plant(self) -> None:
        """The plant's state and its frame 0 (PWM off)."""
        self.pst, self.rng = self.setup.new_plant()
        self.frame = np.zeros(FR_N)
        self.truth = np.zeros(TR_N)
        plant_initial_frame(self.pst, self.setup.mp, self.rng, self.frame, self.truth)
        self.k = 0  # index of the frame held in self.frame

    def _init_mcu_state(self) -> None:
        """Disarmed, PWM off, no fault, no command yet."""
        self.armed = False
        self.pwm_enabled = False  # PWM state for the next period
        self.duty = np.array([0.5, 0.5, 0.5])  # duties for the next period
        self.fault_code = FAULT_NONE
        self.fault_latched = False
        self.fault_count = 0
        self.mode = MODE_IDLE
        self._reset_prev = 0
        self._cmds: dict[int, tuple[np.ndarray, bool]] = {}  # cmd_seq (16 bit) -> duty, enable
        self._applied_seq = 0
        self._last_cmd_k = 0  # period index of the last fresh command
        self._stale_prev = False
        self._status_alive = 0
        self._hb_last: float | None = None
        self._next_status_k = 0
        self._next_fault_repeat_k = 0
        self.stats = EmulatorStats()

    def _init_recording(self, record: bool) -> None:
        self.record = record
        self.rec_frames: list[np.ndarray] = []
        # record=True: wall time (time.time) each sample went out, by wire seq, and the host's
        # answer latency [s]: the answer's bus timestamp (python-can stamps a frame when it
        # is sent) minus its sample's send time, for benchmarks
        self._sent_wall: dict[int, float] = {}
        self.answer_latency_s: list[float] = []
        self.rec_truth: list[np.ndarray] = []

    def _init_messages(self) -> None:
        """The DBC messages the MCU sends and reads."""
        self._msg_sample = self.proto.sample_fd
        self._msg_duty = self.proto.message("DUTY_CMD")
        self._msg_arm = self.proto.message("ARM_MODE")
        self._msg_fault = self.proto.message("FAULT")
        self._msg_status = self.proto.message("STATUS")
        self._msg_ref = self.proto.message("HOST_REF")
        self._msg_prm = self.proto.message("DRIVE_PARAM")
        self._msg_ack = self.proto.message("DRIVE_PARAM_ACK")
        self._prm_names = {
            int(k): str(v) for k, v in self._msg_prm.get_signal_by_name("prm_id").choices.items()
        }

    def _init_window(self) -> None:
        """The sample window: sums over (t_(k-D), t_k] of v_ll and duties (6), PWM on in
        every period, OR of the flags; frame 0 forms the first window on its own."""
        self._win_sum = np.zeros(6)
        self._win_n = 0
        self._win_pwm = True
        self._win_flags = 0
        self._accumulate()

    def _init_split(self) -> None:
        """Split mode: the drive-side controller (engine kernels), its parameters (the
        scenario's design until the host writes DRIVE_PARAMs), references by wire seq."""
        self.control_split = False
        self.split_cp = np.array(self.setup.cp, dtype=float)
        self.split_cs = np.zeros(CS_N)
        self.split_dr = np.zeros(DR_N)
        split_drive_reset(self.split_cs, self.split_dr)
        self._split_out = np.zeros(CO_N)
        self._refs: dict[int, np.ndarray] = {}  # ref_seq (16 bit) -> RF_* row
        self._ref_newest: int | None = None  # ref_seq of the newest HOST_REF not yet taken

    def _warm_kernels(self) -> None:
        """Compile (or load) the plant and the drive-side kernels now, not in the first
        periods (a host waiting for samples would see a stale link); on copies."""
        setup = self.setup
        plant_advance(
            self.pst.copy(),
            setup.mp,
            self.rng.copy(),
            self.duty.copy(),
            False,
            setup.load_t,
            setup.load_y,
            setup.load_cfg,
            self.frame.copy(),
            self.truth.copy(),
        )
        cs, dr = np.zeros(CS_N), np.zeros(DR_N)
        split_drive_reset(cs, dr)
        split_drive_take_reference(cs, dr, np.zeros(RF_N), 0.0)
        split_drive_step(cs, self.split_cp, dr, self.frame.copy(), np.zeros(CO_N))

    def _new_firmware(self) -> Any:
        """The C core as this emulator's MCU, configured like the Python logic: the same
        layout, D, watchdog, over-current trip and heartbeat timeout, the drive parameters
        of the scenario's design (host mode uses only the protections among them)."""

        if self.mcu == "pil":  # the board image on the virtual board (fluxdrive.can.vboard)
            from fluxdrive.can.vboard import VirtualBoard

            make: Any = VirtualBoard
        else:
            make = FirmwareCore
        fw = make(
            self.setup.mp,
            decimation=self.decimation,
            classic=self.layout == "classic",
            cmd_timeout_s=self.cmd_timeout_s,
        )
        values = drive_param_values(self.split_cp)  # the scenario's design, as the Python MCU
        values["OVERCURRENT_A"] = self.overcurrent_a
        values["HEARTBEAT_TIMEOUT_S"] = self.heartbeat_timeout_s or 0.0
        for name, value in values.items():
            status = fw.param_write(name, float(value))
            if status != "OK":
                raise ValueError(f"C drive core refused {name} = {value:g}: {status}")
        return fw

    # ------------------------------------------------------------------ bus I/O

    def _send(self, aid: int, data: bytes, fd: bool) -> None:
        msg = can.Message(
            arbitration_id=aid,
            is_extended_id=False,
            is_fd=fd,
            bitrate_switch=fd,
            data=data,
        )
        try:
            self.bus.send(msg, timeout=self.send_timeout_s)
        except can.CanError:
            self.stats.tx_timeouts += 1

    def _handle(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_extended_id:
            return
        aid = msg.arbitration_id
        if self._fw is not None:
            if aid not in self._rx_ids:  # a flood of other IDs never queues before a duty
                self.stats.filtered_rx += 1
                return
            if aid == ID_HOST_HEARTBEAT:
                self._hb_last = time.monotonic()
            self._fw_rx.append(msg)
            return
        try:
            if aid == ID_DUTY_CMD:
                d = self._msg_duty.decode(bytes(msg.data), decode_choices=False)
                duty = np.array([d["cmd_duty_a"], d["cmd_duty_b"], d["cmd_duty_c"]], float)
                if not np.all(np.isfinite(duty)) or duty.min() < 0.0 or duty.max() > 1.0:
                    self.stats.bad_rx += 1
                    return
                self._cmds[int(d["cmd_seq"])] = (duty, bool(d["cmd_enable"]))
                self.stats.duty_rx += 1
                if self.record:
                    self._answered(int(d["cmd_seq"]), msg.timestamp)
                if len(self._cmds) > 64:  # forget very old ones
                    for key in list(self._cmds)[:-32]:
                        del self._cmds[key]
            elif aid == ID_HOST_REF:
                d = self._msg_ref.decode(bytes(msg.data), decode_choices=False)
                ref = np.zeros(RF_N)
                ref[RF_ID_REF], ref[RF_IQ_REF] = d["ref_id"], d["ref_iq"]
                ref[RF_TH], ref[RF_W] = d["ref_theta"], d["ref_omega"]
                ref[RF_EN] = float(d["ref_enable"])
                ref[RF_MODE] = 3.0  # closed loop, as far as the drive knows
                seq = int(d["ref_seq"])
                self._refs[seq] = ref
                self._ref_newest = seq
                self.stats.ref_rx += 1
                if self.record:
                    self._answered(seq, msg.timestamp)
                if len(self._refs) > 64:
                    for key in list(self._refs)[:-32]:
                        del self._refs[key]
            elif aid == ID_DRIVE_PARAM:
                self._on_param(self._msg_prm.decode(bytes(msg.data), decode_choices=False))
            elif aid == ID_ARM_MODE:
                d = self._msg_arm.decode(bytes(msg.data), decode_choices=False)
                self.stats.arm_rx += 1
                self.control_split = bool(d["control_split"])
                if d["reset_fault"] and not self._reset_prev:
                    self._clear_fault()
                self._reset_prev = int(d["reset_fault"])
                want_classic = bool(d["sample_layout"])
                if (
                    want_classic != (self.layout == "classic")
                    or int(d["decimation"]) != self.decimation
                ):
                    self.stats.layout_mismatch += 1
                if d["arm"] and int(d["arm_key"]) == ARM_KEY and not self.fault_latched:
                    self.armed = True
                    self.mode = int(d["mode"])
                else:
                    if self.armed:
                        self.stats.disarm_rx += 1
                    self._disarm()
                if float(d["cmd_timeout"]) > 0.0:
                    self.cmd_timeout_s = float(d["cmd_timeout"])
            elif aid == ID_HOST_HEARTBEAT:
                self._hb_last = time.monotonic()
        except (ValueError, KeyError, can.CanError, Exception):  # noqa: BLE001 - bad frame
            self.stats.bad_rx += 1

    def _on_param(self, d: dict) -> None:
        """DRIVE_PARAM: write (range-checked) or read, answered by DRIVE_PARAM_ACK with the
        value in effect; statuses as the DBC's pa_status table."""
        pid, seq = int(d["prm_id"]), int(d["prm_seq"])
        name = self._prm_names.get(pid)
        status = 0
        if name is None:
            status, value = 1, 0.0  # UNKNOWN_PARAM
        else:
            value = self._param_value(name)
            if d["prm_write"]:
                v = float(d["prm_value"])
                lo, hi = DRIVE_PARAM_RANGES[name]
                if not np.isfinite(v):
                    status = 4  # NOT_FINITE
                elif not lo <= v <= hi:
                    status = 2  # OUT_OF_RANGE
                elif name in DRIVE_PARAMS_STOPPED and self.pwm_enabled:
                    status = 3  # NOT_WHILE_RUNNING
                else:
                    if name == "HEARTBEAT_TIMEOUT_S":
                        self.heartbeat_timeout_s = v if v > 0.0 else None
                    else:
                        self.split_cp[DRIVE_PARAM_FIELDS[name]] = v
                    value = self._param_value(name)
        self.stats.param_rx += 1
        data = self._msg_ack.encode(
            {"pa_id": pid, "pa_seq": seq, "pa_status": status, "pa_value": float(value)}
        )
        self._send(ID_DRIVE_PARAM_ACK, data, False)

    def _param_value(self, name: str) -> float:
        if name == "HEARTBEAT_TIMEOUT_S":
            return float(self.heartbeat_timeout_s or 0.0)
        return float(self.split_cp[DRIVE_PARAM_FIELDS[name]])

    def _drain(self, timeout: float = 0.0) -> None:
        """Handle everything already received; wait at most ``timeout`` for the first."""
        msg = self.bus.recv(timeout=timeout)
        while msg is not None:
            self._handle(msg)
            msg = self.bus.recv(timeout=0.0)

    # ------------------------------------------------------------------ MCU logic

    def _disarm(self) -> None:
        self.armed = False
        self.pwm_enabled = False
        self.mode = MODE_IDLE

    def _raise_fault(self, code: int, detail: int = 0) -> None:
        self.pwm_enabled = False
        new = not self.fault_latched or self.fault_code != code
        self.fault_code = code
        self.fault_latched = True
        self.armed = False
        if new:
            self.fault_count = min(self.fault_count + 1, 255)
            self.stats.faults += 1
            self.stats.fault_codes.append(code)
            self._send_fault(detail)
            self._next_fault_repeat_k = self.k + int(round(0.1 / self.ts))

    def _clear_fault(self) -> None:
        if self.fault_latched:
            split_drive_reset(self.split_cs, self.split_dr)
            self.fault_latched = False
            self.fault_code = FAULT_NONE
            self._send_fault(0)

    def _send_fault(self, detail: int) -> None:
        data = self._msg_fault.encode(
            {
                "fault_code": self.fault_code,
                "fault_latched": int(self.fault_latched),
                "fault_active": int(self.fault_latched),
                "fault_pwm_disabled": int(self.fault_latched),
                "fault_detail": int(min(max(detail, 0), 65535)),
                "fault_seq": self.k % _SEQ_MOD,
                "fault_count": self.fault_count,
            }
        )
        self._send(ID_FAULT, data, False)

    def _send_status(self) -> None:
        if self.fault_latched:
            state = ST_FAULT
        elif self.pwm_enabled:
            state = ST_RUNNING
        elif self.armed:
            state = ST_ARMED
        else:
            state = ST_IDLE
        data = self._msg_status.encode(
            {
                "st_alive": self._status_alive,
                "st_state": state,
                "st_armed": int(self.armed),
                "st_pwm_enabled": int(self.pwm_enabled),
                "st_fault_latched": int(self.fault_latched),
                "st_sample_layout": int(self.layout == "classic"),
                "st_protocol_version": PROTOCOL_VERSION,
                "st_decimation": self.decimation,
                "st_tx_overruns": 0,
                "st_temp": 35,
                "st_rx_errors": 0,
            }
        )
        self._status_alive = (self._status_alive + 1) % 256
        self._send(ID_STATUS, data, False)

    def sample_payload(self) -> bytes:
        """SAMPLE_FD payload of the frame currently held (frame k), with the window's
        averages (:meth:`window_frame`)."""
        f = self.window_frame()
        sig = {
            "seq": self.k % _SEQ_MOD,
            "i_a": f[FR_IA], "i_b": f[FR_IB], "i_c": f[FR_IC],
            "v_ab": f[FR_VAB], "v_bc": f[FR_VBC], "v_ca": f[FR_VCA],
            "vdc": f[FR_VDC],
            "duty_a": f[FR_DA], "duty_b": f[FR_DB], "duty_c": f[FR_DC],
            "encoder": int((int(f[FR_ENC]) + 2**31) % 2**32 - 2**31),
            "cmd_seq_applied": self._applied_seq,
            "t_mcu": round((self.k * self.ts) % 4294.967295, 6),
            "pwm_enabled": int(f[FR_EN] > 0.5),
            "armed": int(self.armed),
            "fault_active": int(self.fault_latched),
            "adc_clip": int(int(f[FR_FLAGS]) & FRAME_FLAG_ADC_CLIP),
            "cmd_stale": int(self._stale_prev),
            "capture_valid": int(self._win_pwm),
            "control_split": int(self.control_split),
            "mode": self.mode,
            "fault_code": self.fault_code,
        }  # fmt: skip
        return bytes(self._msg_sample.encode(sig, strict=False))

    def _accumulate(self) -> None:
        """Add the frame just sampled to the sample window."""
        f = self.frame
        self._win_sum[0:3] += f[_V_LL]
        self._win_sum[3:6] += f[_DUTIES]
        self._win_n += 1
        self._win_pwm = self._win_pwm and bool(f[FR_EN] > 0.5)
        self._win_flags |= int(f[FR_FLAGS])

    def window_frame(self) -> np.ndarray:
        """Frame k as the sample reports it (either layout): currents, vdc, encoder at
        t_k; line voltages and duties averaged over the window (t_(k-D), t_k]; PWM on
        only if on in all of its periods; flags OR-ed. D = 1: frame k itself."""
        f = self.frame.copy()
        if self._win_n > 1:
            f[_V_LL] = self._win_sum[0:3] / self._win_n
            f[_DUTIES] = self._win_sum[3:6] / self._win_n
        f[FR_EN] = 1.0 if self._win_pwm else 0.0
        f[FR_FLAGS] = float(self._win_flags)
        f[FR_SEQ] = self.k
        return f

    def _reset_window(self) -> None:
        self._win_sum[:] = 0.0
        self._win_n = 0
        self._win_pwm = True
        self._win_flags = 0

    def classic_payloads(self) -> list[tuple[int, bytes]]:
        """The four classic sample frames [(id, 8 bytes)] of frame k with the window
        averages, values saturated to the DBC ranges like the MCU's converters."""
        f = self.window_frame()
        f[_CURRENTS] = np.clip(f[_CURRENTS], -25.0, 25.0)
        f[_V_LL] = np.clip(f[_V_LL], -100.0, 100.0)
        f[FR_VDC] = min(max(f[FR_VDC], 0.0), 100.0)
        f[_DUTIES] = np.clip(f[_DUTIES], 0.0, 1.0)
        flags = {
            "c_armed": int(self.armed),
            "c_fault_active": int(self.fault_latched),
            "c_cmd_stale": int(self._stale_prev),
            "c_capture_valid": int(self._win_pwm),
            "c_control_split": int(self.control_split),
        }
        return self.proto.frame_to_classic_payloads(f, flags)

    def _answered(self, seq: int, stamp: float) -> None:
        t = self._sent_wall.pop(seq, None)
        if t is not None and stamp > 0.0:
            self.answer_latency_s.append(stamp - t)

    def _send_sample(self) -> None:
        if self.record:
            self._sent_wall[self.k % _SEQ_MOD] = time.time()
            if len(self._sent_wall) > 256:
                del self._sent_wall[next(iter(self._sent_wall))]
        if self.layout == "fd":
            self._send(ID_SAMPLE_FD, self.sample_payload(), True)
        else:
            for aid, data in self.classic_payloads():
                self._send(aid, data, False)
        self._reset_window()
        self.stats.samples_sent += 1

    def _protect(self) -> None:
        """Over-current trip on the frame just sampled."""
        imax = float(np.max(np.abs(self.frame[FR_IA : FR_IC + 1])))
        if imax > self.overcurrent_a and not self.fault_latched:
            ph = int(np.argmax(np.abs(self.frame[FR_IA : FR_IC + 1])))
            self._raise_fault(FAULT_OVERCURRENT, ph | (min(int(imax * 10), 16383) << 2))

    def step(self) -> None:
        """One PWM period: send frame k, take the duty answering frame k-1, simulate
        [t_k, t_(k+1)], sample frame k+1. With D > 1 (either layout): samples and duty
        updates only every D-th period (the duty answering sample k-D), duties held in
        between."""
        if self._fw is not None:
            self._step_c()
            return
        k = self.k
        d = self.decimation
        if self.record:
            self.rec_frames.append(self.frame.copy())
            self.rec_truth.append(self.truth.copy())
        boundary = k % d == 0
        if boundary:
            self._send_sample()
        if k >= self._next_status_k:
            self._send_status()
            self._next_status_k = k + int(round(0.1 / self.ts))
        if self.fault_latched and k >= self._next_fault_repeat_k:
            self._send_fault(0)
            self._next_fault_repeat_k = k + int(round(0.1 / self.ts))
        self._drain(0.0)
        split_next = None
        if self.control_split:
            split_next = self._split_step(k, boundary)
        elif boundary:
            self._take_command(k)
        if self.heartbeat_timeout_s is not None and self.armed and self._hb_last is not None:
            if time.monotonic() - self._hb_last > self.heartbeat_timeout_s:
                self._raise_fault(FAULT_HOST_HEARTBEAT_LOST)
        if not self.armed:
            self.pwm_enabled = False
        s = self.setup
        plant_advance(
            self.pst,
            s.mp,
            self.rng,
            self.duty,
            self.pwm_enabled,
            s.load_t,
            s.load_y,
            s.load_cfg,
            self.frame,
            self.truth,
        )
        if split_next is not None:  # the split drive's duty from frame k: next period
            self.duty, self.pwm_enabled = split_next
        self.k = k + 1
        self.stats.periods += 1
        self._accumulate()
        self._protect()

    def _split_step(self, k: int, boundary: bool) -> tuple[np.ndarray, bool]:
        """Split mode, period k: take the newest reference (lockstep: the one answering
        sample k-D, waited for at a sample boundary), run the drive-side current loop on
        frame k; returns (duties, enable) for [t_(k+1), t_(k+2)]."""
        d = self.decimation
        want = None
        if self.lockstep:
            if boundary and k >= d:
                want = (k - d) % _SEQ_MOD
                deadline = time.monotonic() + self.lockstep_wait_s
                while want not in self._refs and not self._stop.is_set():
                    left = deadline - time.monotonic()
                    if left <= 0.0:
                        self.stats.lockstep_timeouts += 1
                        break
                    self._drain(min(left, 0.05))
                if want not in self._refs:
                    want = None
        elif self._ref_newest is not None:
            want = self._ref_newest
        if want is not None:
            ref = self._refs.pop(want)
            self._ref_newest = None
            since = ((k - want) % _SEQ_MOD) * self.ts
            split_drive_take_reference(self.split_cs, self.split_dr, ref, since)
            self._applied_seq = want
            self.stats.refs_applied += 1
        cs, out = self.split_cs, self._split_out
        age = self.split_dr[DR_AGE]
        split_drive_step(cs, self.split_cp, self.split_dr, self.frame, out)
        if cs[CS_MODE] == MODE_FAULT and not self.fault_latched:
            code = int(cs[CS_FAULT])
            detail = int(round(age * 1e4)) if self.split_cp[CP_REF_TIMEOUT] > 0 and code == 9 else 0
            self._raise_fault(code, detail)
        on = bool(out[CO_EN] > 0.5) and self.armed and not self.fault_latched
        if on:
            self.mode = MODE_RUN
        return out[CO_DA : CO_DC + 1].copy(), on

    def _fw_feed(self, hold_refs: bool = False) -> None:
        """Received frames into the C core's RX queue (what does not fit waits).
        ``hold_refs``: HOST_REFs wait for the next sample boundary (lockstep split mode takes
        the answer to sample k-D at boundary k, like the Python MCU; free-running, the core
        takes the newest at any period boundary)."""
        fw = self._fw
        held: collections.deque[can.Message] = collections.deque()
        while self._fw_rx:
            msg = self._fw_rx[0]
            if msg.arbitration_id == ID_DRIVE_PARAM:
                # parameter requests are served between interrupts (a firmware's background
                # loop), so a host waiting for the ACK never stalls a lockstep period
                fw.handle_now(self._fw_rx.popleft())
                self._fw_send()
                continue
            if hold_refs and msg.arbitration_id == ID_HOST_REF:
                held.append(self._fw_rx.popleft())
                continue
            if not fw.push(msg):
                break
            self._fw_rx.popleft()
        self._fw_rx.extendleft(reversed(held))

    def _step_c(self) -> None:
        """One PWM period with the C core as the MCU: sample k in, its period interrupt
        (lockstep: after the host's answer to sample k-D has arrived), the frames it sent
        onto the bus, its PWM into the plant for [t_k, t_(k+1)], sample k+1."""
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
        now_us = int((time.monotonic() - self._t0_wall) * 1e6)
        fw.set_sample(self.frame, now_us)
        fw.period()
        self._fw_send()
        duty, enabled = fw.pwm()
        st = fw.state()
        self.armed = st["armed"]
        self.pwm_enabled = st["pwm_enabled"]
        self.fault_latched = st["fault_latched"]
        self.fault_code = st["fault_code"]
        self.mode = st["mode"]
        self.duty = duty
        s = self.setup
        plant_advance(
            self.pst, s.mp, self.rng, duty, enabled, s.load_t, s.load_y, s.load_cfg,
            self.frame, self.truth,
        )  # fmt: skip
        self.k = k + 1
        self._sync_c_stats()

    def _fw_send(self) -> None:
        """What the C core sent, onto the bus."""
        for msg in self._fw.pop_tx():
            try:
                self.bus.send(msg, timeout=self.send_timeout_s)
            except can.CanError:
                self.stats.tx_timeouts += 1

    def _sync_c_stats(self) -> None:
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

    def _take_command(self, k: int) -> None:
        """At a sample boundary k: take the DUTY_CMD answering the previous sample (k-D);
        in lockstep wait for it. Missing: hold the duties, and the watchdog runs."""
        d = self.decimation
        want = (k - d) % _SEQ_MOD
        if k >= d and want not in self._cmds and self.lockstep:
            deadline = time.monotonic() + self.lockstep_wait_s
            while want not in self._cmds and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0.0:
                    self.stats.lockstep_timeouts += 1
                    break
                self._drain(min(left, 0.05))
        cmd = self._cmds.pop(want, None) if k >= d else None
        # commands answering frames older than k-1 arrived too late: drop them
        for key in [q for q in self._cmds if 0 < (want - q) % _SEQ_MOD < _SEQ_MOD // 2]:
            del self._cmds[key]
            self.stats.duty_late += 1
        if cmd is not None:
            duty, enable = cmd
            self.duty = np.clip(duty, 0.0, 1.0)
            self._applied_seq = want
            self._last_cmd_k = k
            self._stale_prev = False
            self.stats.duty_applied += 1
            if enable and self.armed and not self.fault_latched:
                self.pwm_enabled = True
                self.mode = MODE_RUN
            elif not enable:
                self.pwm_enabled = False
        elif k >= d:
            self._stale_prev = True
            self.stats.stale_periods += 1
            if self.pwm_enabled and (k - self._last_cmd_k) * self.ts >= self.cmd_timeout_s - 1e-12:
                self._raise_fault(FAULT_WATCHDOG, int((k - self._last_cmd_k) * self.ts * 1e4))

    # ------------------------------------------------------------------ running

    def serve(
        self, until: threading.Event, poll_s: float = 0.01, until_armed: bool = False
    ) -> None:
        """Answer the bus (ARM_MODE, DRIVE_PARAM, ...) without running periods, until
        `until` is set (or, with `until_armed`, the host armed the drive): the drive before
        its first period (e.g. configured by the host)."""
        while not until.is_set() and not self._stop.is_set():
            self._drain(poll_s)
            if self._fw is not None:  # the C core answers between interrupts, like this
                while self._fw_rx:
                    self._fw.handle_now(self._fw_rx.popleft())
                self._fw_send()
                if until_armed and self._fw.state()["armed"]:
                    return
            elif until_armed and self.armed:
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
