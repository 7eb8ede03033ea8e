"""Bench bridge supervisor logic (no ROS): CAN frames <-> engine frames, with safety.

:class:`CanBridge` is everything the ``bench_bridge`` ROS node does except ROS:

* **decode** SAMPLE_FD frames into engine frame rows (:data:`fluxdrive.can.protocol.FRAME_FIELDS`,
  seq unwrapped to a 64-bit period index). A burst of frames goes through the vectorised
  numpy codec (:meth:`FluxdriveProtocol.decode_fd`); a lone frame (lockstep, lowest
  latency) through cantools with the same DBC range checks;
* or, with the **classic layout** (``BridgeConfig.layout``; ``"auto"`` follows the bus
  factory's ``fd`` flag), reassemble SAMPLE_C_CUR/VLT/DUTY/AUX into frames
  (:class:`ClassicReassembler`);
* **decimation** (``BridgeConfig.decimation``, either layout; default the DBC's: FD 1,
  classic 8): the samples come every D-th PWM period, so the frames' seq is the *sample*
  index j = k // D (consecutive, what the observers and the controller expect; they must
  run at D*Ts), and a duty for sample j goes out with the wire seq of that sample.
  ARM_MODE tells the MCU the layout and D; a STATUS reporting another layout or D is
  counted (``layout_mismatch``) and latches a fault (the loop would run at the wrong
  sample time), so the drive cannot be armed until it agrees;
* **malformed** frames (wrong length, FD flag clear, out of the DBC range, non-finite; the
  housekeeping frames' signals too; a datagram the bus cannot unpack) are dropped and
  counted by reason;
* **only new samples go on** (:class:`SeqFilter`): sequence gaps are counted and the loop
  continues; duplicates (a repeat, a replay), late (out-of-order) samples and jumps (a
  counter further ahead than ``seq_jump_max`` periods plus what the time since the newest
  sample allows) are counted and dropped, never handed to the graph;
* **stale data**: no valid new sample for ``stale_timeout_s`` while the link was live ->
  STALE fault (latched; the reason names the samples dropped meanwhile), a disable
  DUTY_CMD and a disarm ARM_MODE;
* **arming**: duties go out with ``cmd_enable=1`` only while armed (by :meth:`arm`,
  the node's parameter or service) and no fault is latched; otherwise enable is forced
  to 0 and the suppression counted. ARM_MODE is repeated at 10 Hz with the HOST_HEARTBEAT.
  :meth:`shutdown` disarms (disable + disarm frames) before closing the bus;
* **bus errors / bus-off**: an exception from the bus (or a bus reporting
  ``BusState.ERROR``) closes it; reconnects are attempted through the injectable
  ``bus_factory`` with exponential back-off. The bridge comes back disarmed; lost while
  armed, it latches a STALE fault naming the bus error (the drive goes to PWM off on its
  own command watchdog);
* **floods**: a software bus (``udp_multicast``) gets a receive buffer of
  ``BusFactory.receive_buffer_bytes``, so a burst of foreign frames waits in it instead
  of pushing samples out; frames of other IDs cost one counter each;
* **split mode** (``BridgeConfig.control_split``): ARM_MODE.control_split = 1; the graph's
  current references go out as HOST_REF (:meth:`send_reference`, ref_seq = the wire seq of
  the sample answered, enable forced to 0 unless armed and unfaulted, like duties); the
  drive-side parameters (current gains from ``design_loops``, limits, timeouts) are written
  as DRIVE_PARAM and each waits for its DRIVE_PARAM_ACK (:meth:`set_drive_param`: a
  timeout or the drive's refusal comes back as the reason);
* the drive's **FAULT** frames are kept (code, name, detail) for diagnostics
  (:meth:`drive_fault_text`), including the split-mode reference timeout (WATCHDOG);
* every fault latched or cleared -- the drive's (its FAULT frames) and this supervisor's
  own (stale data, a layout/D disagreement; cleared by :meth:`reset_fault`) -- is queued as
  a :class:`FaultEvent` in ``fault_events`` for the node to publish (DriveFault);
* **counters** for diagnostics (:meth:`diagnostics`).

The bridge is single-threaded: call :meth:`poll` from one thread (the node's CAN
thread); :meth:`send_duty`, :meth:`arm` and friends may be called from others
(sends are serialised by a lock).
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from fluxdrive.can.protocol import (
    ARM_KEY,
    CLASSIC_SAMPLE_IDS,
    DECIMATION_MAX,
    FRAME_FIELDS,
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
    ClassicReassembler,
    FluxdriveProtocol,
    SeqFilter,
    get_protocol,
)
from fluxdrive.core.protocol_constants import (
    FAULT_CHOICES,
    MODE_CALIBRATE_ADC,
    MODE_IDLE,
    MODE_RUN,
    ST_CALIBRATING,
    ST_CHOICES,
)
from fluxdrive.core.schema import param
from fluxdrive.drive.control import (
    FAULT_BAD_SAMPLE,
    FAULT_NAMES,
    FAULT_NONE,
    FAULT_STALE_INPUT,
)

__all__ = [
    "FRAME_FLAG_STALE_COMMAND",
    "BridgeConfig",
    "BusFactory",
    "CanBridge",
    "FaultEvent",
    "bus_factory_from_params",
    "widen_receive_buffer",
]

FRAME_FLAG_STALE_COMMAND = 16
"""Frame ``flags`` bit (= PhaseFrame.STATUS_STALE_COMMAND): the MCU re-applied old duties."""

_SEQ_MOD = 1 << SEQ_BITS
_I_SEQ = FRAME_FIELDS.index("seq")
_I_FLAGS = FRAME_FIELDS.index("flags")
# SAMPLE_FD signal -> frame column, for the cantools single-frame path
_FD_COLS = {
    "i_a": 0, "i_b": 1, "i_c": 2, "v_ab": 3, "v_bc": 4, "v_ca": 5, "vdc": 6,
    "duty_a": 7, "duty_b": 8, "duty_c": 9, "pwm_enabled": 10, "encoder": 11, "seq": 12,
}  # fmt: skip


@dataclass(frozen=True)
class FaultEvent:
    """A fault latched (``latched``) or cleared (code FAULT_NONE) on the bench: ``code`` is a
    DriveFault code (the drive's own codes from 16 up pass through as the drive sent them),
    ``origin`` "drive" (its FAULT frame) or "host" (this supervisor), ``reason`` one line."""

    code: int
    latched: bool
    reason: str
    origin: str


@dataclass
class BridgeConfig:
    """Supervisor settings (the bench_bridge node's parameters of the same names)."""

    stale_timeout_s: float = param(
        0.05,
        unit="s",
        doc="no valid sample for this long (after the first): STALE fault, PWM disabled",
        range=(1e-4, 60.0),
    )
    cmd_timeout_s: float = param(
        1e-3,
        unit="s",
        doc="MCU duty-command watchdog sent in ARM_MODE (0: the MCU's default, 1 ms)",
        range=(0.0, 6.5535),
        live=False,
    )
    heartbeat_period_s: float = param(
        0.1,
        unit="s",
        doc="HOST_HEARTBEAT and ARM_MODE repetition period",
        range=(1e-3, 10.0),
        live=False,
    )
    reconnect_initial_s: float = param(
        0.05,
        unit="s",
        doc="first reconnect delay after the bus is lost",
        range=(1e-3, 60.0),
        live=False,
    )
    reconnect_max_s: float = param(
        2.0,
        unit="s",
        doc="longest reconnect delay (exponential back-off)",
        range=(1e-3, 3600.0),
        live=False,
    )
    reconnect_factor: float = param(
        2.0, unit="-", doc="back-off factor of the reconnect delay", range=(1.0, 10.0), live=False
    )
    send_timeout_s: float = param(
        0.05, unit="s", doc="timeout of one bus send", range=(1e-4, 10.0), live=False
    )
    fast_path_min: int = param(
        4,
        unit="frames",
        doc="bursts of at least this many sample frames use the vectorised numpy decoder",
        range=(1, 1_000_000),
        live=False,
    )
    max_reasons: int = param(
        50,
        unit="-",
        doc="examples of malformed-frame reasons kept for diagnostics",
        range=(0, 10_000),
        live=False,
    )
    layout: str = param(
        "auto",
        unit="",
        doc="sample layout: fd (SAMPLE_FD each period), classic (4-frame layout every D "
        "periods) or auto (classic when the bus factory says fd=False, else fd)",
        choices=("auto", "fd", "classic"),
        live=False,
    )
    decimation: int = param(
        0,
        unit="periods",
        doc="PWM periods per sample, either layout (0: the DBC's default, FD 1 = every "
        "period, which only fits a virtual bus, classic 8; a real 1/5 Mbit/s FD bus needs "
        ">= 4, see docs/can.md); sent in ARM_MODE, the drive must report it in STATUS; "
        "observers and controller must then run at decimation * ts_s",
        range=(0, DECIMATION_MAX),
        live=False,
    )
    control_split: bool = param(
        False,
        unit="",
        doc="split mode: the drive closes the current loop on the graph's current references "
        "(/drive/current_ref -> HOST_REF) and its drive.* parameters",
        live=False,
    )
    param_ack_timeout_s: float = param(
        0.2,
        unit="s",
        doc="how long CanBridge.set_drive_param waits for the DRIVE_PARAM_ACK",
        range=(1e-3, 10.0),
        live=False,
    )
    seq_jump_max: int = param(
        1000,
        unit="periods",
        doc="a sample whose counter is further ahead of the newest than this (plus 1.5 "
        "times the PWM periods since the newest arrived) is a jump: counted and dropped",
        range=(1, 32767),
        live=False,
    )


# a software bus's socket receive buffer (widen_receive_buffer): a flood's worth of datagrams
RECEIVE_BUFFER_BYTES = 32 << 20
# python-can interfaces that take no bit-rate arguments (software buses)
_NO_BITRATE = ("virtual", "udp_multicast")

# a software bus's UDP port, drawn from a wide range: on Linux a udp_multicast socket bound
# to a port receives every group joined on that port, so two buses need two ports, and a
# wide range keeps two runs beside each other apart.  DDS (RTPS) maps domain d to the ports
# 7400 + 250 d and up, the whole range 7400-65535 over the domain ids 0-232, so a port here
# may meet a graph's DDS traffic: the drive drops a datagram that is no CAN message and
# counts it (foreign_datagrams), the bridge counts it malformed ("datagram").  Below
# 7400 there is no DDS but too few ports to keep runs apart
SOFTWARE_BUS_PORTS = (20000, 60000)


def software_bus_endpoint(seed: int | None = None) -> tuple[str, int]:
    """A udp_multicast bus of its own: an administratively scoped group (239.255.x.y) and a
    port in SOFTWARE_BUS_PORTS, drawn from ``seed`` (None: the clock)."""
    import random

    rnd = random.Random(time.monotonic_ns() if seed is None else seed)
    group = f"239.255.{rnd.randint(1, 254)}.{rnd.randint(1, 254)}"
    return group, rnd.randrange(*SOFTWARE_BUS_PORTS)


@dataclass
class BusFactory:
    """A bus factory for :class:`CanBridge` from the node's parameters (callable; opens a
    new python-can bus each call). ``fd`` also selects the bridge's sample layout when
    its ``layout`` is "auto"."""

    interface: str = "virtual"
    channel: str = "fluxdrive"
    bitrate: int = 1_000_000
    fd: bool = True
    data_bitrate: int = 5_000_000
    extra: dict[str, Any] | None = None
    receive_buffer_bytes: int = RECEIVE_BUFFER_BYTES

    def __call__(self) -> can.BusABC:
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel, "fd": self.fd}
        if self.interface not in _NO_BITRATE:
            kw["bitrate"] = self.bitrate
            if self.fd:
                kw["data_bitrate"] = self.data_bitrate
        kw.update(self.extra or {})
        bus = can.Bus(**kw)
        widen_receive_buffer(bus, self.receive_buffer_bytes)
        return bus


def widen_receive_buffer(bus: can.BusABC, size_bytes: int = RECEIVE_BUFFER_BYTES) -> int:
    """A ``udp_multicast`` bus's socket receive buffer raised to ``size_bytes``: the default
    (about 200 kB, a few hundred datagrams) drops samples when a burst of other frames
    arrives faster than the reader takes them (20 000 frames in 0.4 s queue about 20 MB of
    socket buffers on loopback while a Python reader drains them). A process with
    CAP_NET_ADMIN gets the size asked for (SO_RCVBUFFORCE), any other the system's
    ``net.core.rmem_max`` at most. Returns the size in effect (0: not a socket bus)."""
    import socket

    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if not isinstance(sock, socket.socket):
        return 0
    force = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux's number where Python lacks it
    for opt in (force, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, int(size_bytes))
            break
        except OSError:
            continue  # no CAP_NET_ADMIN: the capped SO_RCVBUF
    try:
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    except OSError:
        return 0


def bus_factory_from_params(
    interface: str = "virtual",
    channel: str = "fluxdrive",
    bitrate: int = 1_000_000,
    fd: bool = True,
    data_bitrate: int = 5_000_000,
    **extra: Any,
) -> BusFactory:
    """A :class:`BusFactory` from the node's parameters (``extra``: more python-can
    arguments, e.g. ``port`` / ``hop_limit`` of ``udp_multicast``)."""
    return BusFactory(interface, channel, bitrate, fd, data_bitrate, dict(extra) or None)


class CanBridge:
    """The bench-bridge supervisor (see module doc)."""

    def __init__(
        self,
        bus_factory: Callable[[], can.BusABC],
        config: BridgeConfig | None = None,
        *,
        protocol: FluxdriveProtocol | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = config or BridgeConfig()
        self.bus_factory = bus_factory
        self.proto = protocol or get_protocol()
        self.clock = clock
        self.bus: can.BusABC | None = None
        self._tx_lock = threading.Lock()
        self._arm_lock = threading.RLock()  # arm state change + ARM_MODE send are atomic
        self._init_messages()
        self._init_drive_params()
        self._init_layout(bus_factory)
        self._init_state()

    def _init_messages(self) -> None:
        """The DBC messages the bridge sends and reads, and the DRIVE_PARAM ids and
        ACK statuses by name (from the DBC's value tables)."""
        self._msg_fd = self.proto.sample_fd
        self._msg_duty = self.proto.message("DUTY_CMD")
        self._msg_arm = self.proto.message("ARM_MODE")
        self._msg_fault = self.proto.message("FAULT")
        self._msg_status = self.proto.message("STATUS")
        self._msg_hb = self.proto.message("HOST_HEARTBEAT")
        self._msg_ref = self.proto.message("HOST_REF")
        # an angle within half a step below 2 pi rounds to 2 pi, one past the wire's top
        th = self._msg_ref.get_signal_by_name("ref_theta")
        self._theta_top = 2.0 * math.pi - 0.5 * float(th.scale)
        self._msg_prm = self.proto.message("DRIVE_PARAM")
        self._msg_ack = self.proto.message("DRIVE_PARAM_ACK")
        self.param_ids = {
            str(v): int(k) for k, v in self._msg_prm.get_signal_by_name("prm_id").choices.items()
        }
        self._ack_status = {
            int(k): str(v) for k, v in self._msg_ack.get_signal_by_name("pa_status").choices.items()
        }

    def _init_drive_params(self) -> None:
        """DRIVE_PARAM exchanges in flight, the drive's last fault, the sample's ranges."""
        self._prm_seq = 0
        self._acks: dict[tuple[int, int], tuple[int, float]] = {}  # (id, seq) -> status, value
        self._ack_cv = threading.Condition()
        self._poll_thread: int | None = None  # ident of the thread polling the bus
        self._backlog: list[np.ndarray] = []  # samples polled while waiting for an ACK
        self.drive_fault: dict[str, Any] = {}  # the drive's last FAULT frame
        # faults latched or cleared, oldest first, until the node publishes them
        self.fault_events: deque[FaultEvent] = deque(maxlen=256)
        self._ranges = [
            (s.name, s.minimum, s.maximum)
            for s in self._msg_fd.signals
            if s.minimum is not None or s.maximum is not None
        ]

    def _init_layout(self, bus_factory: Callable[[], can.BusABC]) -> None:
        """The sample layout (auto: the bus's), its decimation D and the MCU's duty
        watchdog (which must outlast a sample period)."""
        layout = self.cfg.layout
        if layout == "auto":
            layout = "fd" if getattr(bus_factory, "fd", True) else "classic"
        if layout not in ("fd", "classic"):
            raise ValueError(f"layout must be 'fd', 'classic' or 'auto', not {layout!r}")
        self.layout = layout
        d = self.cfg.decimation or self.proto.default_decimation(layout)
        if not 1 <= d <= 255:
            raise ValueError(f"decimation must be in 1..255, not {d}")
        self.decimation = d
        """PWM periods per sample (either layout)."""
        self.mcu_cmd_timeout_s = (
            max(self.cfg.cmd_timeout_s, 1.5 * self.decimation / self.proto.pwm_frequency)
            if self.decimation > 1
            else self.cfg.cmd_timeout_s
        )
        self._reasm = ClassicReassembler(protocol=self.proto)
        self._wire: dict[int, int] = {}  # D > 1: sample index j -> wire seq (16 bit)

    def _init_state(self) -> None:
        """Disarmed, no fault, no sample seen, counters at zero."""
        self.armed = False
        self.fault: str = ""  # latched host-side fault reason ("" = none)
        self.drive_mismatch: str = ""  # the last STATUS's layout/D disagreement ("" = none)
        # the last STATUS's protocol version disagreement ("" = none)
        self.protocol_mismatch: str = ""
        # arming needs the drive parameters written and read back (write_drive_params)
        self.require_params = False
        self.params_verified = False
        self._mismatch_run = 0  # consecutive disagreeing STATUS frames
        self.mcu: dict[str, Any] = {}  # last MCU status / fault / sample flags
        # STATUS.st_state of the drive's STATUS frames, newest last (calibrate watches it)
        self.status_states: deque[int] = deque(maxlen=256)
        self._calibrating = False  # the ARM_MODE repeated is the calibration request
        self.calibrated = False  # calibrate() done since the last (re)connect
        # which samples are new; the stream is never followed across a jump: it goes
        # stale and faults, and a reset or a reconnect starts it again
        self.seq = SeqFilter(step=self.decimation, max_jump=self.cfg.seq_jump_max)
        self._seq_out = 0  # seq of the last frame handed out (the sample index j = k // D)
        # the bus's receive timestamp [s] of the oldest sample the last poll took (0.0:
        # none): a host timing its answers counts from there
        self.poll_first_rx_s = 0.0
        self._last_valid_t: float | None = None
        self._next_hb_t = 0.0
        self._hb_alive = 0
        self._arm_counter = 0
        self._reset_pulse = False
        self._backoff = self.cfg.reconnect_initial_s
        self._next_connect_t = 0.0
        self.counters: Counter[str] = Counter()
        self.malformed_reasons: Counter[str] = Counter()
        self.malformed_examples: list[str] = []
        self.last_error = ""

    @property
    def newest_sample(self) -> int:
        """Sample index j of the newest frame handed out (0 before the first)."""
        return self._seq_out

    # ------------------------------------------------------------------ connection

    @property
    def connected(self) -> bool:
        return self.bus is not None

    def connect(self) -> bool:
        """Open the bus through the factory now (no back-off). True on success."""
        try:
            self.bus = self.bus_factory()
        except Exception as exc:  # noqa: BLE001 - any driver error means "not connected"
            self.bus = None
            self.counters["connect_failures"] += 1
            self.last_error = f"connect: {exc!r}"
            self._schedule_reconnect()
            return False
        self.counters["connects"] += 1
        self._backoff = self.cfg.reconnect_initial_s
        self._last_valid_t = None  # the stale timer restarts with the first frame
        self.seq.reanchor()
        self._reasm = ClassicReassembler(protocol=self.proto)
        self._next_hb_t = 0.0
        self.drive_mismatch = ""  # the drive's next STATUS tells again
        self.protocol_mismatch = ""
        self.params_verified = False  # another drive may answer now
        self.calibrated = False
        self._mismatch_run = 0
        return True

    def _schedule_reconnect(self) -> None:
        self._next_connect_t = self.clock() + self._backoff
        self.counters["backoff_ms"] = int(self._backoff * 1e3)
        self._backoff = min(self._backoff * self.cfg.reconnect_factor, self.cfg.reconnect_max_s)

    def _bus_failed(self, exc: BaseException | str) -> None:
        """Bus error / bus-off: close, disarm (the MCU disarms on heartbeat loss too),
        and schedule a reconnect with back-off."""
        self.counters["bus_errors"] += 1
        self.last_error = f"bus: {exc!r}" if not isinstance(exc, str) else exc
        if self.armed:
            self.counters["disarmed_by_bus_error"] += 1
            if not self.fault:  # the reason stays: no arming until a reset
                self.counters["faults"] += 1
                self.fault = f"CAN bus lost while armed ({self.last_error})"
                self.fault_events.append(
                    FaultEvent(
                        FAULT_STALE_INPUT,
                        True,
                        f"{self.fault}: disarmed, PWM off by the drive's command watchdog",
                        "host",
                    )
                )
        self.armed = False
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001 - already broken
                pass
        self._schedule_reconnect()

    # ------------------------------------------------------------------ sending

    def _send(self, aid: int, data: bytes, fd: bool = False) -> bool:
        bus = self.bus
        if bus is None:
            self.counters["tx_while_disconnected"] += 1
            return False
        msg = can.Message(
            arbitration_id=aid, is_extended_id=False, is_fd=fd, bitrate_switch=fd, data=data
        )
        try:
            with self._tx_lock:
                bus.send(msg, timeout=self.cfg.send_timeout_s)
        except can.CanOperationError as exc:
            # a full queue / TX timeout is not a dead bus; anything else is
            if "timed out" in str(exc).lower() or "full" in str(exc).lower():
                self.counters["tx_timeouts"] += 1
                return False
            self._bus_failed(exc)
            return False
        except (can.CanError, OSError) as exc:
            self._bus_failed(exc)
            return False
        self.counters["tx_frames"] += 1
        return True

    def send_duty(self, seq: int, duty: Sequence[float] | np.ndarray, enable: bool) -> bool:
        """DUTY_CMD answering sample ``seq``. ``enable`` only reaches the wire while armed
        and unfaulted (else forced to 0, counted in ``enable_suppressed``); duties are
        clamped to [0, 1], non-finite ones replaced by 0.5 with PWM off."""
        d = [float(x) for x in duty]
        en = bool(enable)
        if not all(math.isfinite(x) for x in d):
            d = [0.5, 0.5, 0.5]
            en = False
            self.counters["duty_nonfinite"] += 1
        if en and (not self.armed or self.fault):
            en = False
            self.counters["enable_suppressed"] += 1
        d = [min(max(x, 0.0), 1.0) for x in d]
        data = self._msg_duty.encode(
            {"cmd_seq": self._wire_seq(int(seq)), "cmd_duty_a": d[0], "cmd_duty_b": d[1],
             "cmd_duty_c": d[2], "cmd_enable": int(en)},
            strict=False,
        )  # fmt: skip
        ok = self._send(ID_DUTY_CMD, data)
        if ok:
            self.counters["duty_tx"] += 1
            if en:
                self.counters["duty_tx_enabled"] += 1
        return ok

    def _wire_seq(self, seq: int) -> int:
        """16-bit wire seq of the sample a duty answers (sample index j -> its seq)."""
        if self.decimation > 1:
            return self._wire.get(seq, seq * self.decimation) % _SEQ_MOD
        return seq % _SEQ_MOD

    def send_reference(
        self, seq: int, id_ref: float, iq_ref: float, theta: float, omega: float, enable: bool
    ) -> bool:
        """HOST_REF answering sample ``seq`` (split mode): current references [A], the frame's
        electrical angle at the sample instant [rad] and speed [rad/s]. ``enable`` reaches
        the wire only while armed and unfaulted (else 0, counted in ``enable_suppressed``);
        non-finite values go out as PWM off (``ref_nonfinite``)."""
        vals = [float(id_ref), float(iq_ref), float(theta), float(omega)]
        en = bool(enable)
        if not all(math.isfinite(x) for x in vals):
            vals = [0.0, 0.0, 0.0, 0.0]
            en = False
            self.counters["ref_nonfinite"] += 1
        if en and (not self.armed or self.fault):
            en = False
            self.counters["enable_suppressed"] += 1
        theta = vals[2] % (2.0 * math.pi)
        if theta >= self._theta_top:  # the same angle as 0, which the wire can carry
            theta = 0.0
        data = self._msg_ref.encode(
            {"ref_seq": self._wire_seq(int(seq)), "ref_id": vals[0], "ref_iq": vals[1],
             "ref_theta": theta, "ref_omega": vals[3],
             "ref_enable": int(en)},
            strict=False,
        )  # fmt: skip
        ok = self._send(ID_HOST_REF, data, fd=True)
        if ok:
            self.counters["ref_tx"] += 1
            if en:
                self.counters["ref_tx_enabled"] += 1
        return ok

    def read_drive_param(
        self, name: str, timeout_s: float | None = None
    ) -> tuple[bool, str, float]:
        """Read drive parameter ``name`` (DRIVE_PARAM with prm_write = 0): (answered, reason,
        its value on the drive), like :meth:`set_drive_param` without the write."""
        return self.set_drive_param(name, 0.0, timeout_s, write=False)

    def set_drive_param(
        self, name: str, value: float, timeout_s: float | None = None, *, write: bool = True
    ) -> tuple[bool, str, float]:
        """Write drive parameter ``name`` (DRIVE_PARAM value table) and wait for its
        DRIVE_PARAM_ACK: (accepted, reason, value in effect). Refused without sending if
        the name is unknown or the value not finite; a refusal names the drive's status.
        Another thread may be polling the bus (the node's CAN thread); otherwise this
        polls it itself, keeping the samples for the next :meth:`poll`.  ``write`` False:
        a read (:meth:`read_drive_param`)."""
        pid = self.param_ids.get(name)
        if pid is None:
            return False, f"unknown drive parameter {name!r}; known: {sorted(self.param_ids)}", 0.0
        if not math.isfinite(float(value)):
            return False, f"{name}: value {value!r} is not finite", 0.0
        with self._ack_cv:
            self._prm_seq = (self._prm_seq + 1) % 256
            seq = self._prm_seq
            self._acks.pop((pid, seq), None)
        data = self._msg_prm.encode(
            {"prm_id": pid, "prm_seq": seq, "prm_write": int(write), "prm_value": float(value)}
        )
        if not self._send(ID_DRIVE_PARAM, data):
            return False, f"{name}: DRIVE_PARAM could not be sent ({self.last_error})", 0.0
        self.counters["param_tx"] += 1
        wait = self.cfg.param_ack_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + wait
        other_polls = self._poll_thread not in (None, threading.get_ident())
        while True:
            with self._ack_cv:
                ack = self._acks.pop((pid, seq), None)
                left = deadline - time.monotonic()
                if ack is None and left > 0 and other_polls:
                    self._ack_cv.wait(min(left, 0.05))
                    ack = self._acks.pop((pid, seq), None)
            if ack is not None:
                break
            if left <= 0:
                self.counters["param_ack_timeouts"] += 1
                return False, f"{name}: no DRIVE_PARAM_ACK within {wait:g} s", 0.0
            if not other_polls:
                frames = self._poll_bus(min(left, 0.01))
                if frames.shape[0]:
                    self._backlog.append(frames)
        status, v = ack
        text = self._ack_status.get(status, f"status {status}")
        if status != 0:
            self.counters["param_refused"] += 1
            what = f"{name} = {value:g}" if write else f"a read of {name}"
            return False, f"the drive refused {what}: {text} (in effect: {v:g})", v
        self.counters["param_ok"] += 1
        return True, f"{name} = {v:g} on the drive", v

    def write_drive_params(
        self, values: dict[str, float], timeout_s: float | None = None
    ) -> tuple[bool, str]:
        """Write every drive parameter of ``values`` (each acknowledged), then read each
        back: (True, what was done) or (False, the first refusal, missing answer or value
        the drive holds other than the one written -- float32 rounding aside -- in one
        line). With :attr:`require_params`, :meth:`arm` refuses until this has passed since
        the last (re)connect."""
        self.params_verified = False
        for name, v in values.items():
            ok, why, _ = self.set_drive_param(name, v, timeout_s)
            if not ok:
                return False, f"drive parameters not taken: {why}"
        tightened: list[str] = []
        for name, v in values.items():
            ok, why, got = self.read_drive_param(name, timeout_s)
            if not ok:
                return False, f"drive parameters not read back: {why}"
            if _same_float32(got, v):
                continue
            if _tighter(name, v, got):
                # a protection limit the board holds stricter than asked (its rating: a
                # DRIVE_PARAM only ever tightens it): the drive protects there, said here
                tightened.append(f"{name} {got:g} (asked {v:g})")
                continue
            self.counters["param_mismatch"] += 1
            return False, (
                f"drive parameter mismatch: {name} written {v:g}, the drive holds {got:g}: "
                f"not armed"
            )
        self.params_verified = True
        self.counters["param_tightened"] += len(tightened)
        note = f"; the board's stricter limits hold: {', '.join(tightened)}" if tightened else ""
        return True, f"{len(values)} drive parameters written and read back{note}"

    def drive_fault_text(self) -> str:
        """The drive's latched fault as one line ("" when none): name, code, detail."""
        f = self.drive_fault
        if not f or not f.get("code") or not f.get("latched"):
            return ""
        code = int(f["code"])
        name = fault_name(code)
        detail = int(f.get("detail", 0))
        extra = ""
        if code == 9:  # WATCHDOG: duty (host mode) or reference (split mode) timeout
            what = "reference" if self.cfg.control_split else "duty command"
            extra = f" ({what} timeout: {detail * 0.1:.1f} ms without one)"
        elif detail:
            extra = f" (detail {detail})"
        return f"drive fault {code} {name}{extra}, PWM off (latched at sample {f.get('seq')})"

    def _send_arm(self, arm: bool, reset_fault: bool = False) -> bool:
        """ARM_MODE: armed (RUN) or not; while :meth:`calibrate` runs, its request instead
        (CALIBRATE_ADC with the arm key: the drive stays disarmed, PWM off)."""
        self._arm_counter = (self._arm_counter + 1) % 256
        cal = self._calibrating and not arm
        mode = MODE_CALIBRATE_ADC if cal else MODE_RUN if arm else MODE_IDLE
        data = self._msg_arm.encode(
            {"arm": int(arm or cal), "reset_fault": int(reset_fault),
             "sample_layout": int(self.layout == "classic"),
             "control_split": int(self.cfg.control_split),
             "mode": mode, "arm_key": ARM_KEY if arm or cal else 0,
             "cmd_timeout": min(self.mcu_cmd_timeout_s, 6.5535),
             "decimation": self.decimation, "arm_counter": self._arm_counter},
            strict=False,
        )  # fmt: skip
        return self._send(ID_ARM_MODE, data)

    def arm(self) -> tuple[bool, str]:
        """Arm the drive (host side and ARM_MODE). Refused while :meth:`arm_refusal` says
        why, or with :attr:`require_params` until the drive's parameters were written and
        read back (:meth:`write_drive_params`)."""
        why = self.arm_refusal()
        if why:
            return False, why
        if self.require_params and not self.params_verified:
            return False, "drive parameters not written and read back since the last connect"
        with self._arm_lock:
            self.armed = True
            if not self._send_arm(True):
                self.armed = False
                return False, "ARM_MODE could not be sent"
        self.counters["arms"] += 1
        return True, "armed"

    def calibrate(self, timeout_s: float = 5.0, status_wait_s: float = 1.0) -> tuple[bool, str]:
        """The drive's current/capture offset calibration, the motor at standstill: ARM_MODE
        mode CALIBRATE_ADC with the arm key, repeated every heartbeat period while it runs
        (any other ARM_MODE ends a calibration unfinished), until a STATUS says CALIBRATING
        and a later one says it is over (done), or a FAULT frame says why it failed
        (ADC_FAULT: an offset out of range). The drive stays disarmed, PWM off, throughout;
        a disarmed ARM_MODE ends the request. ``timeout_s`` counts from the drive's first
        STATUS, which must come within ``status_wait_s``. Refused while armed. Another thread
        may be polling the bus (the node's CAN thread); otherwise this polls it itself,
        keeping the samples for the next :meth:`poll`. (done, one line)"""
        if self.armed:
            return False, "no offset calibration while armed: disarm first"
        why = self.arm_refusal()
        if why:
            return False, why
        if self.mcu.get("fault_latched"):
            return False, f"the drive has a fault latched ({self.drive_fault_text()}): reset it"
        other_polls = self._poll_thread not in (None, threading.get_ident())
        self.status_states.clear()
        faults0 = self.counters["fault_rx"]
        with self._arm_lock:
            self._calibrating = True
            self._send_arm(False)
        t0 = time.monotonic()
        t_first: float | None = None
        try:
            while True:
                if other_polls:
                    time.sleep(0.005)
                else:
                    frames = self._poll_bus(0.005)
                    if frames.shape[0]:
                        self._backlog.append(frames)
                states = list(self.status_states)
                now = time.monotonic()
                if states and t_first is None:
                    t_first = now
                if ST_CALIBRATING in states and states[-1] != ST_CALIBRATING:
                    self.counters["calibrations"] += 1
                    self.calibrated = True
                    return True, f"offsets calibrated (drive {ST_CHOICES[states[-1]]})"
                if self.counters["fault_rx"] > faults0 and self.drive_fault_text():
                    return False, f"the offset calibration failed: {self.drive_fault_text()}"
                if t_first is None and now - t0 > status_wait_s:
                    return False, f"no drive answers: no STATUS frame within {status_wait_s:g} s"
                if t_first is not None and now - t_first > timeout_s:
                    seen = " -> ".join(dict.fromkeys(ST_CHOICES.get(x, str(x)) for x in states))
                    return False, (
                        f"the drive did not calibrate within {timeout_s:g} s (its states: {seen})"
                    )
        finally:
            with self._arm_lock:
                self._calibrating = False
                if self.bus is not None:
                    self._send_arm(False)

    def arm_refusal(self) -> str:
        """Why :meth:`arm` would refuse before anything is written to the drive ("" =
        nothing): a latched fault, another protocol version or layout/D in the drive's last
        STATUS, the bus down."""
        if self.fault:
            return f"fault latched: {self.fault}; reset it first"
        if self.protocol_mismatch:
            return self.protocol_mismatch
        if self.drive_mismatch:
            return self.drive_mismatch
        if not self.connected:
            return "CAN bus not connected"
        return ""

    def disarm(self, reason: str = "") -> tuple[bool, str]:
        """Disarm: a disable DUTY_CMD (for the last sample) and ARM_MODE arm=0."""
        with self._arm_lock:
            self.armed = False
            self.counters["disarms"] += 1
            if self.connected:
                self.send_duty(self._seq_out, (0.5, 0.5, 0.5), False)
                self._send_arm(False)
        return True, reason or "disarmed"

    def reset_fault(self) -> tuple[bool, str]:
        """Clear the host-side latched fault and pulse ARM_MODE.reset_fault (the drive
        reports its own clearing with a FAULT frame)."""
        if self.fault:
            self.fault_events.append(
                FaultEvent(FAULT_NONE, False, f"'{self.fault}' cleared by a reset", "host")
            )
        self.fault = ""
        self.seq.reanchor()  # a stream that went stale on dropped samples starts again
        if self.connected:
            self._send_arm(False, reset_fault=True)
            self._send_arm(False, reset_fault=False)
        return True, "fault reset"

    def _raise_fault(self, reason: str, code: int) -> None:
        if not self.fault:
            self.counters["faults"] += 1
            self.fault_events.append(FaultEvent(code, True, f"{reason}: PWM off, latched", "host"))
        self.fault = reason
        self.disarm(reason)

    # ------------------------------------------------------------------ receiving

    def poll(self, timeout: float = 0.0, max_frames: int = 4096) -> np.ndarray:
        """Receive what is there (waiting up to ``timeout`` for the first message),
        run the supervisor checks and return the valid samples as (N, 14) frames."""
        self._poll_thread = threading.get_ident()
        frames = self._poll_bus(timeout, max_frames)
        if self._backlog:
            frames = np.vstack([*self._backlog, frames])
            self._backlog.clear()
        return frames

    def _poll_bus(self, timeout: float = 0.0, max_frames: int = 4096) -> np.ndarray:
        now = self.clock()
        if self.bus is None:
            if now >= self._next_connect_t:
                self.connect()
            if self.bus is None:
                if timeout > 0:
                    time.sleep(min(timeout, max(self._next_connect_t - now, 0.0)))
                return np.empty((0, len(FRAME_FIELDS)))
        samples: list[can.Message] = []
        bus = self.bus
        sample_ids = (ID_SAMPLE_FD,) if self.layout == "fd" else CLASSIC_SAMPLE_IDS
        # when the bus was last seen with nothing waiting: staleness is judged at that
        # instant, not after this thread got the CPU back -- a bridge held up (load, the
        # GIL) while samples queued in its socket is late, the drive is not silent
        t_empty = self.clock()
        try:
            msg = self._recv(bus, timeout)
            while msg is not None:
                if msg.arbitration_id in sample_ids and not msg.is_error_frame:
                    samples.append(msg)
                else:
                    self._handle_other(msg)
                if len(samples) >= max_frames:
                    break
                t_empty = self.clock()
                msg = self._recv(bus, 0.0)
            state = getattr(bus, "state", None)
            if state == can.BusState.ERROR:
                raise can.CanOperationError("bus-off (BusState.ERROR)")
        except (can.CanError, OSError) as exc:
            frames = self._decode(samples)
            self._bus_failed(exc)
            return frames
        self.poll_first_rx_s = samples[0].timestamp if samples else 0.0
        frames = self._decode(samples)
        self.tick(t_empty)
        return frames

    def _recv(self, bus: can.BusABC, timeout: float) -> can.Message | None:
        """One message; a datagram the bus cannot unpack (anything on a software bus's
        group and port) is malformed, not a dead bus."""
        try:
            return bus.recv(timeout=timeout)
        except can.CanOperationError as exc:
            if "could not unpack" not in str(exc):
                raise
            self._malformed("datagram", f"not a CAN message: {exc.__cause__ or exc}")
            return None

    def _handle_other(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.counters["error_frames"] += 1
            return
        aid = msg.arbitration_id
        try:
            if aid == ID_STATUS:
                d = _decode_checked(self._msg_status, msg.data)
                self.counters["status_rx"] += 1
                self.status_states.append(int(d["st_state"]))
                self.mcu.update(
                    state=int(d["st_state"]), armed=int(d["st_armed"]),
                    pwm_enabled=int(d["st_pwm_enabled"]),
                    fault_latched=int(d["st_fault_latched"]),
                    protocol_version=int(d["st_protocol_version"]),
                    sample_layout=int(d["st_sample_layout"]),
                    decimation=int(d["st_decimation"]),
                )  # fmt: skip
                self._check_drive_layout(bool(d["st_sample_layout"]), int(d["st_decimation"]))
                self._check_protocol_version(int(d["st_protocol_version"]))
            elif aid == ID_FAULT:
                d = _decode_checked(self._msg_fault, msg.data)
                self.counters["fault_rx"] += 1
                self.mcu.update(
                    fault_code=int(d["fault_code"]),
                    fault_latched=int(d["fault_latched"]),
                    fault_count=int(d["fault_count"]),
                )
                self._note_drive_fault(d)
                if d["fault_code"] and d["fault_latched"] and self.armed:
                    self.armed = False  # the MCU disarmed itself
                    self.counters["disarmed_by_mcu_fault"] += 1
            elif aid == ID_DRIVE_PARAM_ACK:
                d = _decode_checked(self._msg_ack, msg.data)
                self.counters["param_ack_rx"] += 1
                with self._ack_cv:
                    key = (int(d["pa_id"]), int(d["pa_seq"]))
                    self._acks[key] = (int(d["pa_status"]), float(d["pa_value"]))
                    while len(self._acks) > 64:
                        del self._acks[next(iter(self._acks))]
                    self._ack_cv.notify_all()
            elif aid in (ID_DUTY_CMD, ID_ARM_MODE, ID_HOST_HEARTBEAT, ID_HOST_REF, ID_DRIVE_PARAM):
                self.counters["rx_own_traffic"] += 1
            elif aid == ID_SAMPLE_FD or aid in CLASSIC_SAMPLE_IDS:
                self.counters["layout_mismatch"] += 1  # samples of the other layout
            else:
                self.counters["rx_other"] += 1
        except Exception as exc:  # noqa: BLE001 - a bad housekeeping frame is counted
            self._malformed("housekeeping", f"0x{aid:03X}: {exc}")

    def _note_drive_fault(self, d: dict[str, Any]) -> None:
        """A FAULT frame: keep the first of a latched fault's repeats; a new latched fault,
        and the clearing of one, become fault events."""
        f = self.drive_fault
        was = int(f["code"]) if f and f["code"] and f["latched"] else 0
        same = bool(was) and was == int(d["fault_code"])
        if not (same and d["fault_latched"]):  # a repeat keeps the first's details
            self.drive_fault = {
                "code": int(d["fault_code"]),
                "latched": int(d["fault_latched"]),
                "detail": int(d["fault_detail"]),
                "seq": int(d["fault_seq"]),
            }
        if d["fault_code"] and d["fault_latched"] and not same:
            self.counters["drive_faults_rx"] += 1
            ev = FaultEvent(int(d["fault_code"]), True, self.drive_fault_text(), "drive")
            self.fault_events.append(ev)
        elif was and not (d["fault_code"] and d["fault_latched"]):
            name = fault_name(was)
            ev = FaultEvent(FAULT_NONE, False, f"drive fault {was} {name} cleared", "drive")
            self.fault_events.append(ev)

    def _malformed(self, kind: str, detail: str) -> None:
        self.counters["malformed"] += 1
        self.malformed_reasons[kind] += 1
        if len(self.malformed_examples) < self.cfg.max_reasons:
            self.malformed_examples.append(detail)

    def _decode(self, msgs: list[can.Message]) -> np.ndarray:
        n = len(msgs)
        if n == 0:
            return np.empty((0, len(FRAME_FIELDS)))
        if self.layout == "classic":
            return self._decode_classic(msgs)
        self.counters["rx_samples"] += n
        ok_fd = [bool(m.is_fd) for m in msgs]
        if n >= self.cfg.fast_path_min:
            frames, res = self.proto.decode_fd([bytes(m.data) for m in msgs])
            valid = res.report.valid.copy()
            reasons = res.report.reasons
            stale = res.column("cmd_stale")
            names = res.names
            self.counters["fast_path_frames"] += n
            for i in range(n):
                if not ok_fd[i] and valid[i]:
                    valid[i] = False
                    reasons[i] = "sent as a classic CAN frame (FD flag clear)"
            for bad in np.flatnonzero(~valid).tolist():
                self._malformed(_reason_kind(reasons[bad]), reasons[bad])
            frames = frames[valid]
            frames[:, _I_FLAGS] = (frames[:, _I_FLAGS].astype(np.int64) & FRAME_FLAG_ADC_CLIP) | (
                np.where(stale[valid] > 0.5, FRAME_FLAG_STALE_COMMAND, 0)
            )
            vals, stale_v = res.values[valid], stale[valid] > 0.5

            def info(i: int) -> dict[str, Any]:
                return dict(zip(names, vals[i], strict=True))
        else:
            rows, infos = [], []
            for i, m in enumerate(msgs):
                got = self._decode_one(m, ok_fd[i])
                if got is not None:
                    rows.append(got[0])
                    infos.append(got[1])
            frames = np.vstack(rows) if rows else np.empty((0, len(FRAME_FIELDS)))
            stale_v = np.array([bool(d["cmd_stale"]) for d in infos], dtype=bool)

            def info(i: int) -> dict[str, Any]:
                return infos[i]

        if frames.shape[0]:
            frames, keep = self._hand_out(frames)
            if frames.shape[0]:  # what the drive says of itself: from new samples only
                self._note_info(info(int(np.flatnonzero(keep)[-1])))
                self.counters["mcu_cmd_stale"] += int(np.count_nonzero(stale_v[keep]))
        return frames

    def _hand_out(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Valid samples of either layout: only the new ones go on (:class:`SeqFilter`;
        duplicates, late ones and jumps are counted and dropped), their seq unwrapped to
        the period index k, then k -> the sample index j = k // D (the wire seq of each j
        kept for the duty answering it). Returns (the new samples, the taken mask)."""
        wire = frames[:, _I_SEQ].astype(np.int64)
        now = self.clock()
        keep, k = self.seq.accept(wire, np.full(wire.size, now), self.proto.pwm_frequency)
        if not keep.all():
            frames, wire = frames[keep], wire[keep]
            if not frames.shape[0]:
                return frames, keep
        frames[:, _I_SEQ] = k[keep]
        if self.decimation > 1:
            j = np.floor_divide(frames[:, _I_SEQ].astype(np.int64), self.decimation)
            frames[:, _I_SEQ] = j
            for jj, w in zip(j.tolist(), wire.tolist(), strict=True):
                self._wire[jj] = w
            while len(self._wire) > 512:
                del self._wire[next(iter(self._wire))]
        self._seq_out = int(frames[-1, _I_SEQ])
        self._last_valid_t = now
        self.counters["frames_out"] += frames.shape[0]
        return frames, keep

    def _check_protocol_version(self, version: int) -> None:
        """STATUS: the drive must speak this host's protocol version (the DBC's); otherwise
        every frame may mean something else. Refuses :meth:`arm`; while armed, latches a
        fault (disable + disarm)."""
        if version == PROTOCOL_VERSION:
            self.protocol_mismatch = ""
            return
        self.counters["protocol_mismatch"] += 1
        self.protocol_mismatch = (
            f"protocol version mismatch: the drive speaks version {version}, this host "
            f"version {PROTOCOL_VERSION}"
        )
        if self.armed and not self.fault:
            self._raise_fault(self.protocol_mismatch, FAULT_BAD_SAMPLE)

    def _check_drive_layout(self, classic: bool, decimation: int) -> None:
        """STATUS: the drive must run the layout and D this bridge asked for; otherwise
        the samples would be read at the wrong sample time. Every disagreeing STATUS is
        counted and refuses :meth:`arm`; two in a row (the drive had a whole STATUS
        period to apply ARM_MODE) latch a fault: disable + disarm, and it comes back after
        a reset for as long as the drive disagrees."""
        if classic == (self.layout == "classic") and decimation == self.decimation:
            self.drive_mismatch = ""
            self._mismatch_run = 0
            return
        self.counters["layout_mismatch"] += 1
        self._mismatch_run += 1
        self.drive_mismatch = (
            f"layout mismatch: the drive runs the {'classic' if classic else 'fd'} layout "
            f"with D={decimation}, this bridge expects the {self.layout} layout with "
            f"D={self.decimation}"
        )
        if self._mismatch_run >= 2 and not self.fault:
            # samples of another layout or rate than the loop is set for: bad samples
            self._raise_fault(self.drive_mismatch, FAULT_BAD_SAMPLE)

    def _decode_classic(self, msgs: list[can.Message]) -> np.ndarray:
        """Reassemble classic sample parts into frames (seq: see :meth:`_hand_out`)."""
        ra = self._reasm
        rows: list[np.ndarray] = []
        auxes: list[dict[str, Any]] = []
        for m in msgs:
            self.counters["rx_sample_parts"] += 1
            n_bad, n_inc = ra.malformed, ra.incomplete
            row = ra.feed(m.arbitration_id, bytes(m.data))
            if ra.malformed > n_bad:
                reason = ra.reasons[-1] if ra.reasons else "malformed classic part"
                ra.reasons.clear()
                self._malformed(_reason_kind(reason), reason)
            if ra.incomplete > n_inc:
                self.counters["classic_incomplete"] += ra.incomplete - n_inc
            if row is None:
                continue
            aux = dict(ra.last_aux)
            row[_I_FLAGS] = (int(row[_I_FLAGS]) & FRAME_FLAG_ADC_CLIP) | (
                FRAME_FLAG_STALE_COMMAND if aux.get("c_cmd_stale") else 0
            )
            rows.append(row)
            auxes.append(aux)
        if not rows:
            return np.empty((0, len(FRAME_FIELDS)))
        frames = np.vstack(rows)
        self.counters["rx_samples"] += frames.shape[0]
        frames, keep = self._hand_out(frames)
        for i in np.flatnonzero(keep).tolist():  # what the drive says: new samples only
            aux = auxes[i]
            self.mcu["sample_armed"] = int(aux.get("c_armed", 0))
            self.mcu["sample_fault_active"] = int(aux.get("c_fault_active", 0))
            if aux.get("c_cmd_stale"):
                self.counters["mcu_cmd_stale"] += 1
        return frames

    def _decode_one(self, m: can.Message, is_fd: bool) -> tuple[np.ndarray, dict] | None:
        data = bytes(m.data)
        if len(data) != self._msg_fd.length:
            self._malformed("length", f"wrong length {len(data)} bytes (expected 64)")
            return None
        if not is_fd:
            self._malformed("not_fd", "sent as a classic CAN frame (FD flag clear)")
            return None
        d = self._msg_fd.decode(data, decode_choices=False)
        for name, lo, hi in self._ranges:
            v = d[name]
            if not math.isfinite(v):
                self._malformed("nonfinite", f"{name} is {v}")
                return None
            if (lo is not None and v < lo) or (hi is not None and v > hi):
                self._malformed("range", f"{name}={v:g} outside [{lo:g}, {hi:g}]")
                return None
        row = np.empty(len(FRAME_FIELDS))
        for name, col in _FD_COLS.items():
            row[col] = d[name]
        row[_I_FLAGS] = (int(d["adc_clip"]) & FRAME_FLAG_ADC_CLIP) | (
            FRAME_FLAG_STALE_COMMAND if d["cmd_stale"] else 0
        )
        return row, d

    def _note_info(self, d: dict[str, Any]) -> None:
        self.mcu["sample_armed"] = int(d["armed"])
        self.mcu["sample_fault_code"] = int(d["fault_code"])
        self.mcu["cmd_seq_applied"] = int(d["cmd_seq_applied"])

    # ------------------------------------------------------------------ periodic

    def tick(self, now: float | None = None) -> None:
        """Supervisor checks: stale data, heartbeat/ARM_MODE repetition, reconnect."""
        now = self.clock() if now is None else now
        if self.bus is None:
            if now >= self._next_connect_t:
                self.connect()
            return
        t = self._last_valid_t
        if t is not None and now - t > self.cfg.stale_timeout_s and not self.fault:
            self.counters["stale_faults"] += 1
            self._last_valid_t = None
            why = f"stale data: no valid sample for {now - t:.3f} s"
            if self.seq.reject_run:
                why += (
                    f" ({self.seq.reject_run} samples dropped meanwhile, the last: "
                    f"{self.seq.last_reason})"
                )
            self._raise_fault(why, FAULT_STALE_INPUT)
        if now >= self._next_hb_t:
            self._next_hb_t = now + self.cfg.heartbeat_period_s
            self._hb_alive = (self._hb_alive + 1) % 256
            self._send(
                ID_HOST_HEARTBEAT,
                self._msg_hb.encode(
                    {"hb_alive": self._hb_alive, "hb_protocol_version": PROTOCOL_VERSION}
                ),
            )
            with self._arm_lock:
                if self.bus is not None:
                    self._send_arm(self.armed and not self.fault)

    def shutdown(self) -> None:
        """Disarm (disable + disarm frames), then close the bus."""
        if self.bus is not None:
            self.disarm("shutdown")
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.shutdown()

    # ------------------------------------------------------------------ diagnostics

    def state(self) -> str:
        if self.bus is None:
            return "disconnected"
        if self.fault:
            return "fault"
        return "armed" if self.armed else "idle"

    def diagnostics(self) -> dict[str, Any]:
        """Flat dict of counters and state for diagnostic_msgs KeyValues."""
        st = self.seq.stats
        out: dict[str, Any] = {
            "state": self.state(),
            "armed": self.armed,
            "fault": self.fault,
            "layout": self.layout,
            "decimation": self.decimation,
            "control_split": bool(self.cfg.control_split),
            "drive_fault": self.drive_fault_text(),
            "drive_mismatch": self.drive_mismatch,
            "protocol_mismatch": self.protocol_mismatch,
            "params_verified": self.params_verified,
            "seq_gaps": st.gaps,
            "seq_lost": st.lost,
            "seq_duplicates": st.duplicates,
            "seq_out_of_order": st.out_of_order,
            "seq_jumps": st.jumps,
            "seq_rejected": st.rejected,
            "last_error": self.last_error,
        }
        base = (
            "rx_samples",
            "frames_out",
            "malformed",
            "faults",
            "stale_faults",
            "bus_errors",
            "connects",
            "connect_failures",
            "duty_tx",
            "duty_tx_enabled",
            "enable_suppressed",
            "tx_timeouts",
            "error_frames",
            "fast_path_frames",
            "layout_mismatch",
            "protocol_mismatch",
            "param_mismatch",
            "param_tightened",
        )
        out.update({k: 0 for k in base})
        out.update({k: int(v) for k, v in sorted(self.counters.items())})
        out.update({f"malformed_{k}": int(v) for k, v in sorted(self.malformed_reasons.items())})
        out.update({f"mcu_{k}": v for k, v in sorted(self.mcu.items())})
        return out


def _decode_checked(msg: Any, data: bytes | bytearray) -> dict[str, Any]:
    """A housekeeping frame decoded with every signal checked against the DBC: finite and
    within its range (ValueError naming the signal otherwise)."""
    d = msg.decode(bytes(data), decode_choices=False)
    for sig in msg.signals:
        v = float(d[sig.name])
        if not math.isfinite(v):
            raise ValueError(f"{msg.name}.{sig.name} is {v}")
        lo, hi = sig.minimum, sig.maximum
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ValueError(f"{msg.name}.{sig.name}={v:g} outside [{lo}, {hi}]")
    return d


HOST_HEARTBEAT_TIMEOUT_S = 0.5
"""The drive's HEARTBEAT_TIMEOUT_S a bridge writes: five of its 10 Hz HOST_HEARTBEATs
(``BridgeConfig.heartbeat_period_s``) missed, the drive turns PWM off (supervised from
arming, in both modes)."""


def fault_name(code: int) -> str:
    """A drive fault code's name: the engine's words where it has the code, else the DBC's
    value table (``GATE_DRIVER`` -> "gate driver")."""
    name = FAULT_NAMES.get(code)
    if name is None:
        name = FAULT_CHOICES.get(code, f"code {code}").lower().replace("_", " ")
    return name


# drive parameters that are protection limits, by the direction in which the drive's own
# value is the stricter one (a board rating below what the host asked for, a bus floor above)
_UPPER_LIMITS = frozenset(
    {"OVERCURRENT_A", "CUR_LIMIT_A", "VDC_MAX_V", "I2T_LIMIT_PU2S", "REF_TIMEOUT_S",
     "HEARTBEAT_TIMEOUT_S", "MAX_DUTY"}
)  # fmt: skip
_LOWER_LIMITS = frozenset({"VDC_MIN_V"})


def _tighter(name: str, asked: float, held: float) -> bool:
    """The drive holds a stricter protection limit than the one written."""
    if name in _UPPER_LIMITS:
        return held < asked
    if name in _LOWER_LIMITS:
        return held > asked
    return False


def _same_float32(a: float, b: float) -> bool:
    """Equal as the drive stores them (float32), within its rounding."""
    fa, fb = float(np.float32(a)), float(np.float32(b))
    return abs(fa - fb) <= 1e-6 * max(abs(fa), abs(fb))


def _reason_kind(reason: str) -> str:
    r = reason.lower()
    if "length" in r:
        return "length"
    if "fd flag" in r:
        return "not_fd"
    if " is nan" in r or " is inf" in r or " is -inf" in r:
        return "nonfinite"
    if "outside" in r:
        return "range"
    return "other"
