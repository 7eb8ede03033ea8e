"""The C drive firmware (``firmware/``) in the loop: host build and ctypes binding.

:func:`build_host` builds the firmware for this machine with CMake into
``.ws/firmware/host`` (the core as a static library, the core + the software-in-the-loop
HAL as ``libfluxdrive_sil.so``, the C unit tests), generating the CAN codec from the DBC
with this interpreter's cantools; it rebuilds only when a firmware source or the DBC
changed (a content hash, like the bootstrap's stamps).

:class:`FirmwareCore` is one drive MCU: the C core plus its SIL HAL, both in caller-owned
memory (the C side has no heap). Per PWM period the driver

* hands it the raw readings of sample k (:meth:`FirmwareCore.set_sample` converts the
  plant's frame to ADC counts, capture ticks and encoder counts with the plant's own sensor
  scales, ``fluxdrive.drive.plant`` MP_*),
* moves received CAN frames in (:meth:`push`), runs the two contexts as the target does
  (:meth:`period`: the background context, which takes the received frames and hands
  DUTY_CMDs and HOST_REFs to the interrupt lock-free, then the period interrupt, which
  never reads the CAN controller itself),
* reads the PWM back (:meth:`pwm`: duties and enable for the period now starting) and the
  frames the core sent (:meth:`pop_tx`).

The SIL's timer model is a real timer's (firmware/include/fd_hal.h): what the interrupt of
sample k writes sits in the compare preload registers until the update event at t_(k+1),
so the period [t_k, t_(k+1)] runs on what the previous interrupt wrote; only a cleared
enable acts at once (the gates open in the running period).

``DriveEmulator`` (fluxdrive.can.emulator) does exactly that with the project's plant.
No ROS imports.
"""

from __future__ import annotations

import ctypes
import fcntl
import hashlib
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from fluxdrive.core.paths import ROOT
from fluxdrive.core.protocol_constants import PA_CHOICES, PRM_CHOICES
from fluxdrive.drive import plant as pl

__all__ = [
    "FIRMWARE_DIR",
    "PARAM_IDS",
    "FirmwareBuildError",
    "FirmwareCore",
    "build_host",
    "host_build_dir",
    "load_library",
    "sensor_scales",
]

FIRMWARE_DIR = ROOT / "firmware"
PARAM_IDS: dict[str, int] = {name: pid for pid, name in PRM_CHOICES.items()}
"""DRIVE_PARAM prm_id by name (the DBC's value table, generated)."""
READ_ONLY_PARAMS = (
    "CAL_OFFSET_A", "CAL_OFFSET_B", "CAL_OFFSET_C", "CAL_CAPTURE_AB", "CAL_CAPTURE_BC",
    "CAL_CAPTURE_CA", "CAL_DONE", "PARAM_SOURCE", "FAULT_LOG", "CAN_TEC", "CAN_BUS_OFFS",
)  # fmt: skip
"""Read-only DRIVE_PARAMs (a write is READ_ONLY): the offset calibration's result
(ARM_MODE mode CALIBRATE_ADC: current offsets [ADC counts], capture offsets [ticks],
CAL_DONE 1 once calibrated), PARAM_SOURCE (0 defaults, 1 loaded from storage, 2 defaults
because the stored record's CRC failed), FAULT_LOG (entries held; a read over CAN is
followed by one FAULT_LOG frame per entry), the CAN controller's TEC and bus-off count."""
DRIVE_ONLY_PARAMS = ("MAX_DUTY", "PARAM_SAVE", *READ_ONLY_PARAMS)
"""DRIVE_PARAMs not in the engine's ``DRIVE_PARAM_RANGES``: MAX_DUTY, the largest
upper-switch duty (the drive's default 0.95 unless written), PARAM_SAVE (write 1 with PWM
off: the parameters into the drive's storage with a CRC), and the read-only ones."""


class FirmwareBuildError(RuntimeError):
    """The host build of firmware/ failed (the message names the log)."""


def host_build_dir() -> Path:
    return ROOT / ".ws" / "firmware" / "host"


def _source_hash(extra: str) -> str:
    h = hashlib.sha256(extra.encode())
    files = sorted(
        p for p in FIRMWARE_DIR.rglob("*") if p.is_file() and "__pycache__" not in p.parts
    )
    generated_from = [
        ROOT / "config" / "can" / "fluxdrive.dbc",
        ROOT / "tools" / "gen_protocol.py",
        ROOT / "python" / "fluxdrive" / "can" / "protocol" / "generate.py",
    ]
    for p in [*files, *generated_from]:
        h.update(str(p.relative_to(ROOT)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def build_host(force: bool = False) -> Path:
    """Build firmware/ for this machine (CMake, system C compiler) into
    :func:`host_build_dir`; a no-op while no source changed. Returns the build dir."""
    bdir = host_build_dir()
    bdir.mkdir(parents=True, exist_ok=True)
    stamp = bdir / ".fluxdrive-stamp"
    want = _source_hash(sys.executable)
    lib = bdir / "libfluxdrive_sil.so"
    if not force and lib.is_file() and stamp.is_file() and stamp.read_text() == want:
        return bdir
    log = bdir / "build.log"
    with open(bdir.parent / "host.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # concurrent test processes build once
        if not force and lib.is_file() and stamp.is_file() and stamp.read_text() == want:
            return bdir
        steps = [
            ["cmake", "-S", str(FIRMWARE_DIR), "-B", str(bdir), f"-DFD_PYTHON={sys.executable}",
             "-DCMAKE_BUILD_TYPE=Release"],
            ["cmake", "--build", str(bdir), "-j", "2"],
        ]  # fmt: skip
        with open(log, "w") as out:
            for cmd in steps:
                rc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, check=False)
                if rc.returncode != 0:
                    raise FirmwareBuildError(
                        f"firmware host build failed: {' '.join(cmd[:2])} (log: {log})"
                    )
        stamp.write_text(want)
    return bdir


_LIB: ctypes.CDLL | None = None


class _Config(ctypes.Structure):
    """fd_config_t (firmware/include/fd_core.h)."""

    _fields_ = [
        ("period_us", ctypes.c_uint32),
        ("ts_s", ctypes.c_float),
        ("decimation", ctypes.c_uint8),
        ("classic_layout", ctypes.c_uint8),
        ("current_lsb_a", ctypes.c_float),
        ("current_offset_counts", ctypes.c_int32 * 3),
        ("current_clip_counts", ctypes.c_int32),
        ("vdc_lsb_v", ctypes.c_float),
        ("pwm_period_ticks", ctypes.c_uint32),
        ("cmd_timeout_us", ctypes.c_uint32),
        ("status_period", ctypes.c_uint32),
        ("current_adc_max_counts", ctypes.c_int32),
        ("oc_limit_a", ctypes.c_float),
        ("vdc_max_v", ctypes.c_float),
        ("vdc_min_v", ctypes.c_float),
        ("vdc_modulation_min_v", ctypes.c_float),
        ("temp_max_c", ctypes.c_int32),
        ("temp_hysteresis_c", ctypes.c_int32),
        ("bootstrap_periods", ctypes.c_uint32),
        ("ref_max_age_periods", ctypes.c_uint32),
        ("ref_horizon_periods", ctypes.c_uint32),
        ("cal_periods", ctypes.c_uint32),
        ("cal_max_offset_counts", ctypes.c_int32),
        ("require_calibration", ctypes.c_uint8),
    ]


_STAT_NAMES = (
    "periods", "samples_sent", "duty_rx", "duty_applied", "duty_late", "stale_periods",
    "ref_rx", "arm_rx", "bad_rx", "tx_overruns", "layout_mismatch", "disarm_rx", "faults",
    "param_rx", "refs_applied", "ref_old", "ref_future", "adc_clipped", "duty_limited",
    "cmd_ring_full", "ref_handover_busy", "bg_frames", "can_bus_offs", "param_saves",
)  # fmt: skip


class _Stats(ctypes.Structure):
    """fd_stats_t."""

    _fields_ = [(n, ctypes.c_uint32) for n in _STAT_NAMES]


class _Frame(ctypes.Structure):
    """fd_can_frame_t (firmware/include/fd_hal.h)."""

    _fields_ = [
        ("id", ctypes.c_uint32),
        ("len", ctypes.c_uint8),
        ("fd", ctypes.c_uint8),
        ("data", ctypes.c_uint8 * 64),
    ]


class CurState(ctypes.Structure):
    """fd_cur_state_t: the current PIs' integrators [V]."""

    _fields_ = [("id_i", ctypes.c_float), ("iq_i", ctypes.c_float)]


class CurParams(ctypes.Structure):
    """fd_cur_params_t (the engine's CP_* of the current loop)."""

    _fields_ = [
        (n, ctypes.c_float)
        for n in ("kp", "ki", "l_hat", "lambda_hat", "decouple", "advance", "tdcomp_s")
    ]


class CurOut(ctypes.Structure):
    """fd_cur_out_t."""

    _fields_ = [
        ("duty", ctypes.c_float * 3),
        ("i_d", ctypes.c_float),
        ("i_q", ctypes.c_float),
        ("v_d", ctypes.c_float),
        ("v_q", ctypes.c_float),
    ]


def _c_signatures() -> dict[str, tuple[Any, list[Any]]]:
    """The SIL library's functions: name -> (return type, argument types)."""
    P, U32, I32, F = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int32, ctypes.c_float
    U8, U16 = ctypes.c_uint8, ctypes.c_uint16
    I32P = ctypes.POINTER(ctypes.c_int32)
    U32P = ctypes.POINTER(ctypes.c_uint32)
    U8P = ctypes.POINTER(ctypes.c_uint8)
    FP = ctypes.POINTER(F)
    return {
        "fd_sil_sizeof": (ctypes.c_size_t, []),
        "fd_core_sizeof": (ctypes.c_size_t, []),
        "fd_sil_init": (None, [P]),
        "fd_config_default": (None, [ctypes.POINTER(_Config)]),
        "fd_core_init": (None, [P, ctypes.POINTER(_Config), P]),
        "fd_core_period": (None, [P]),
        "fd_core_background": (ctypes.c_uint, [P]),
        "fd_core_param_write": (ctypes.c_int, [P, ctypes.c_int, F]),
        "fd_core_param_read": (ctypes.c_int, [P, ctypes.c_int, FP]),
        "fd_sil_has_answer": (ctypes.c_int, [P, P, U16]),
        "fd_core_handle_frame": (None, [P, ctypes.POINTER(_Frame)]),
        "fd_core_flags": (U32, [P]),
        "fd_core_stats": (ctypes.POINTER(_Stats), [P]),
        "fd_core_period_index": (U32, [P]),
        "fd_sil_restart_period_index": (None, [P]),
        "fd_sil_set_inputs": (None, [P, I32P, I32, I32P, I32, I32, I32, U32]),
        "fd_sil_set_time": (None, [P, U32]),
        "fd_sil_get_pwm": (None, [P, U32P, I32P]),
        "fd_sil_rx_push": (ctypes.c_int, [P, U32, U8P, U32, U32]),
        "fd_sil_inject": (None, [P, I32, I32, I32, I32, I32]),
        "fd_sil_set_break": (None, [P, I32, I32]),
        "fd_sil_tx_pop": (ctypes.c_int, [P, U32P, U8P, U32P, U32P]),
        # state, params, i_alpha, i_beta, th, we, id_ref, iq_ref, vdc, ts, out
        "fd_current_loop": (
            None,
            [ctypes.POINTER(CurState), ctypes.POINTER(CurParams)]
            + [F] * 8
            + [ctypes.POINTER(CurOut)],
        ),
        "fd_i2t_step": (F, [F, F, F, F, F]),
        "fd_sil_decode_host": (ctypes.c_int, [U32, U8P, U32, FP]),
        "fd_encode_fault": (ctypes.c_int, [U8P] + [U8] * 4 + [U16] * 2 + [U8]),
        "fd_encode_status": (ctypes.c_int, [U8P] + [U8] * 7 + [U16, ctypes.c_int8, U8]),
        "fd_encode_sample_fd": (ctypes.c_int, [U8P, U16, FP, I32, U16, U32, U8, U8, U8]),
        "fd_encode_sample_classic": (ctypes.c_int, [U8P, U16, FP, I32, U8]),
        "fd_encode_param_ack": (ctypes.c_int, [U8P, U8, U8, U8, F]),
    }


def load_library() -> ctypes.CDLL:
    """The SIL shared library (built first if needed), with argument types declared."""
    global _LIB
    if _LIB is not None:
        return _LIB
    lib = ctypes.CDLL(str(build_host() / "libfluxdrive_sil.so"))
    for name, (res, args) in _c_signatures().items():
        fn = getattr(lib, name)
        fn.restype = res
        fn.argtypes = args
    _LIB = lib
    return lib


@dataclass(frozen=True)
class SensorScales:
    """The plant's sensor scales as a drive's calibration: counts <-> SI."""

    current_lsb_a: float
    current_mid_counts: int
    vdc_lsb_v: float
    capture_period_ticks: int


def sensor_scales(mp: np.ndarray) -> SensorScales:
    """Calibration of the plant's sensors (``fluxdrive.drive.plant`` MP_*): current ADC
    step and mid-scale, bus ADC step, capture ticks per period (the timer tick of the
    capture model when on, else the capture's levels per period)."""
    lsb = float(mp[pl.MP_ADC_LSB])
    mid = int(round(float(mp[pl.MP_ADC_RANGE]) / lsb))
    if mp[pl.MP_CAP_ON] > 0.0:
        ticks = int(round(float(mp[pl.MP_TS]) / float(mp[pl.MP_CAP_TICK])))
    else:
        ticks = int(round(float(mp[pl.MP_CAP_LEVELS])))
    return SensorScales(lsb, mid, float(mp[pl.MP_VDC_LSB]), ticks)


def _buffer(size: int) -> ctypes.Array[ctypes.c_char]:
    # 16-byte aligned: ctypes' buffers come from malloc, which aligns to 16 on this ABI
    return ctypes.create_string_buffer(size)


class FirmwareCore:
    """One C drive core with its SIL HAL (see the module doc)."""

    def __init__(
        self,
        mp: np.ndarray,
        *,
        decimation: int = 1,
        classic: bool = False,
        cmd_timeout_s: float = 1e-3,
        pwm_period_ticks: int = 50_000,
        bootstrap_periods: int | None = 0,
        require_calibration: bool = False,
        status_period_s: float = 0.1,
    ) -> None:
        self.lib = load_library()
        self.scales = sensor_scales(mp)
        self.ts = float(mp[pl.MP_TS])
        period_us = self.ts * 1e6
        if abs(period_us - round(period_us)) > 1e-6:
            raise ValueError(f"the firmware needs a whole number of us per period, not {period_us}")
        cfg = _Config()
        self.lib.fd_config_default(ctypes.byref(cfg))
        cfg.period_us = int(round(period_us))
        cfg.ts_s = self.ts
        cfg.decimation = int(decimation)
        cfg.classic_layout = int(bool(classic))
        cfg.current_lsb_a = self.scales.current_lsb_a
        for j in range(3):
            cfg.current_offset_counts[j] = self.scales.current_mid_counts
        cfg.current_clip_counts = self.scales.current_mid_counts
        cfg.vdc_lsb_v = self.scales.vdc_lsb_v
        cfg.pwm_period_ticks = int(pwm_period_ticks)
        cfg.cmd_timeout_us = int(round(cmd_timeout_s * 1e6))
        cfg.status_period = max(1, int(round(status_period_s / self.ts)))
        # the board limits of the plant's sensors: over-current cap 5 % below the current
        # ADC's full scale, bus over-voltage 2 % below the bus ADC's, no duty below 5 % of
        # it; the under-voltage trip is the host's VDC_MIN_V (the plant has no stage rating)
        mid = self.scales.current_mid_counts
        cfg.current_adc_max_counts = 2 * mid - 1  # a converter's highest result (12 bit: 4095)
        full_a = mid * self.scales.current_lsb_a
        bus_v = float(mp[pl.MP_VDC_RANGE])
        cfg.oc_limit_a = 0.95 * full_a
        cfg.vdc_max_v = 0.98 * bus_v
        cfg.vdc_min_v = 0.0
        cfg.vdc_modulation_min_v = 0.05 * bus_v
        # no bootstrap charge unless asked (None: the core's default, the board's): the
        # in-process loops the SIL is compared with have none
        if bootstrap_periods is not None:
            cfg.bootstrap_periods = int(bootstrap_periods)
        # offset calibration (ARM_MODE mode CALIBRATE_ADC): offsets up to 10 % of the
        # current ADC's half range; arming an uncalibrated drive is refused (FAULT
        # NOT_CALIBRATED) only with require_calibration, since the emulator's hosts arm
        # without calibrating first
        cfg.cal_max_offset_counts = max(1, mid // 10)
        cfg.require_calibration = int(bool(require_calibration))
        self.config = cfg
        self.pwm_period_ticks = int(pwm_period_ticks)
        self._sil = _buffer(int(self.lib.fd_sil_sizeof()))
        self._core = _buffer(int(self.lib.fd_core_sizeof()))
        self.lib.fd_sil_init(self._sil)
        self.lib.fd_core_init(self._core, ctypes.byref(cfg), self._sil)
        self._cur = (ctypes.c_int32 * 3)()
        self._ticks = (ctypes.c_int32 * 3)()
        self._cmp = (ctypes.c_uint32 * 3)()
        self._en = ctypes.c_int32()
        self._id = ctypes.c_uint32()
        self._len = ctypes.c_uint32()
        self._fd = ctypes.c_uint32()
        self._data = (ctypes.c_uint8 * 64)()
        # the timer's active registers (loaded at the last update event): duties, enable;
        # the port starts the timer at half duty with the outputs off
        self._active: tuple[np.ndarray, bool] = (np.full(3, 0.5), False)
        self._interrupts = 0
        self._adc_held: dict[int, int] = {}

    # ---------------------------------------------------------------- parameters
    def param_write(self, name: str | int, value: float) -> str:
        """Write a DRIVE_PARAM as a received frame would; returns the pa_status name."""
        pid = PARAM_IDS[name] if isinstance(name, str) else int(name)
        return PA_CHOICES[self.lib.fd_core_param_write(self._core, pid, float(value))]

    def param_read(self, name: str | int) -> float:
        pid = PARAM_IDS[name] if isinstance(name, str) else int(name)
        v = ctypes.c_float()
        self.lib.fd_core_param_read(self._core, pid, ctypes.byref(v))
        return float(v.value)

    # ---------------------------------------------------------------- per period
    def set_sample(self, frame: np.ndarray, time_us: int, temp_c: int = 35) -> None:
        """Sample k for the next :meth:`period`: the plant's frame as raw counts (exact:
        the plant's readings are whole ADC/capture steps)."""
        s = self.scales
        vdc = float(frame[pl.FR_VDC])
        for j in range(3):
            self._cur[j] = int(round(frame[pl.FR_IA + j] / s.current_lsb_a)) + s.current_mid_counts
            frac = float(frame[pl.FR_VAB + j]) / vdc if vdc > 0.0 else 0.0
            self._ticks[j] = int(round(frac * s.capture_period_ticks))
        for j, counts in self._adc_held.items():
            self._cur[j] = counts
        enc = (int(frame[pl.FR_ENC]) + 2**31) % 2**32 - 2**31
        self.lib.fd_sil_set_inputs(
            self._sil,
            self._cur,
            int(round(vdc / s.vdc_lsb_v)),
            self._ticks,
            s.capture_period_ticks,
            enc,
            int(temp_c),
            int(time_us) & 0xFFFFFFFF,
        )

    def inject(
        self,
        *,
        gate_fault: bool = False,
        can_tec: int = 0,
        can_rec: int = 0,
        can_bus_off: bool = False,
        overrun: bool = False,
    ) -> None:
        """Fault injection into the SIL HAL: the gate driver's fault input, the CAN
        controller's error counters and bus-off state (held until the next call), and a
        missed deadline reported at the end of the next period interrupt."""
        self.lib.fd_sil_inject(
            self._sil, int(gate_fault), int(can_tec), int(can_rec), int(can_bus_off), int(overrun)
        )

    def hold_adc(self, phase: int, counts: int | None) -> None:
        """Fault injection: the current ADC's result of `phase` (0..2) held at `counts`
        from the next sample on, whatever the current (a converter fault); None releases
        it."""
        if counts is None:
            self._adc_held.pop(phase, None)
        else:
            self._adc_held[phase] = int(counts)

    def set_break(self, threshold_a: float) -> None:
        """The hardware over-current comparator (into the timer's break input) at
        ``threshold_a`` on any phase (0: none): the period whose reading crosses it runs
        with the gates open, and the core latches OVERCURRENT."""
        s = self.scales
        counts = int(round(threshold_a / s.current_lsb_a)) if threshold_a > 0.0 else 0
        self.lib.fd_sil_set_break(self._sil, s.current_mid_counts, counts)

    def set_time(self, time_us: int) -> None:
        self.lib.fd_sil_set_time(self._sil, int(time_us) & 0xFFFFFFFF)

    def period(self) -> None:
        """One period as the target runs it: the background context until it has no
        received frame left (what the main loop does between interrupts), the timer's
        update event at t_k (the preload the previous interrupt wrote goes active), then
        the period interrupt on the sample set last."""
        while self.lib.fd_core_background(self._core):
            pass
        if self._interrupts:
            self._active = self.written()
        self.lib.fd_core_period(self._core)
        self._interrupts += 1

    def background(self) -> int:
        """One call of the background context alone (at most 16 received frames handled);
        returns how many it handled."""
        return int(self.lib.fd_core_background(self._core))

    def written(self) -> tuple[np.ndarray, bool]:
        """Duties (compare / period ticks) and enable the last interrupt wrote (the timer's
        preload registers: in force from the next update event)."""
        self.lib.fd_sil_get_pwm(self._sil, self._cmp, ctypes.byref(self._en))
        p = float(self.pwm_period_ticks)
        return np.array([self._cmp[0] / p, self._cmp[1] / p, self._cmp[2] / p]), bool(
            self._en.value
        )

    def pwm(self) -> tuple[np.ndarray, bool]:
        """Duties and enable over the period now starting, [t_k, t_(k+1)] after the
        interrupt of sample k: the duties its predecessor wrote, on only if both it and its
        predecessor enabled (a cleared enable opens the switches at once)."""
        duty, enabled = self._active
        return duty.copy(), enabled and self.written()[1]

    def push(self, msg: can.Message) -> bool:
        """A received frame into the core's RX queue; False if the queue is full."""
        data = bytes(msg.data)
        buf = (ctypes.c_uint8 * max(len(data), 1)).from_buffer_copy(data or b"\0")
        return bool(
            self.lib.fd_sil_rx_push(
                self._sil, msg.arbitration_id, buf, len(data), int(bool(msg.is_fd))
            )
        )

    def handle_now(self, msg: can.Message) -> None:
        """Serve a received frame at once in the background context, between period
        interrupts (``fd_core_handle_frame``); its answer is in :meth:`pop_tx`."""
        data = bytes(msg.data)[:64]
        f = _Frame(msg.arbitration_id, len(data), int(bool(msg.is_fd)))
        ctypes.memmove(f.data, data, len(data))
        self.lib.fd_core_handle_frame(self._core, ctypes.byref(f))

    def pop_tx(self) -> list[can.Message]:
        """The frames the core sent since the last call, in order."""
        out = []
        while self.lib.fd_sil_tx_pop(
            self._sil,
            ctypes.byref(self._id),
            self._data,
            ctypes.byref(self._len),
            ctypes.byref(self._fd),
        ):
            fd = bool(self._fd.value)
            out.append(
                can.Message(
                    arbitration_id=self._id.value,
                    is_extended_id=False,
                    is_fd=fd,
                    bitrate_switch=fd,
                    data=bytes(self._data[: self._len.value]),
                )
            )
        return out

    def has_answer(self, seq: int) -> bool:
        """The host's answer to sample ``seq`` is waiting (lockstep)."""
        return bool(self.lib.fd_sil_has_answer(self._sil, self._core, seq & 0xFFFF))

    # ---------------------------------------------------------------- state
    @property
    def k(self) -> int:
        return int(self.lib.fd_core_period_index(self._core))

    def restart_period_index(self) -> None:
        """The lockstep bench's run origin: the core's period counter back to 0, what it
        schedules moved with it (``fd_sil_restart_period_index``)."""
        self.lib.fd_sil_restart_period_index(self._core)

    def state(self) -> dict[str, int | bool]:
        f = int(self.lib.fd_core_flags(self._core))
        return {
            "armed": bool(f & 1),
            "pwm_enabled": bool(f & 2),
            "fault_latched": bool(f & 4),
            "split": bool(f & 8),
            "fault_code": (f >> 8) & 0xFF,
            "mode": (f >> 16) & 0xF,
        }

    def stats(self) -> dict[str, int]:
        st = self.lib.fd_core_stats(self._core).contents
        return {n: int(getattr(st, n)) for n in _STAT_NAMES}
