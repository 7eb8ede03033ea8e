"""Engine arrays <-> the per-sample messages, as CDR bytes (see cdr.py).

The engine's rows (fluxdrive.drive.plant FR_*/TR_*, fluxdrive.drive.observers ES_*,
fluxdrive.drive.control CO_*) are float64 and so are the message fields, so a row survives a
trip through a message bit for bit (booleans are 0.0/1.0 in the rows; seq is an exact
integer below 2^53).

Time stamps: header.stamp is the sample instant t_k = k Ts, computed in integer nanoseconds
from the sequence number (Ts = 100 us is a whole number of ns).
"""

from __future__ import annotations

import math

import numpy as np
from fluxdrive.drive.control import (
    CO_DA,
    CO_DB,
    CO_DC,
    CO_EN,
    CO_FAULT,
    CO_ID,
    CO_ID_REF,
    CO_IQ,
    CO_IQ_REF,
    CO_MODE,
    CO_N,
    CO_TH,
    CO_VD,
    CO_VQ,
    CO_W_FB,
    CO_W_REF,
)
from fluxdrive.drive.observers import ES_N, ES_VALID
from fluxdrive.drive.plant import (
    FLAG_CLIP,
    FR_EN,
    FR_ENC,
    FR_FLAGS,
    FR_N,
    FR_SEQ,
    TR_IA,
    TR_IB,
    TR_IC,
    TR_N,
    TR_T,
    TR_TE,
    TR_THETA_E,
    TR_TL,
    TR_WM,
)

from . import topics
from .cdr import Codec, Decoder

STATUS_SENSOR_CLIP = 1
STATUS_SIMULATED = 2
STATUS_STALE_COMMAND = 16

try:  # fault codes of fluxdrive.drive.control (= DriveFault codes) -> text
    from fluxdrive.drive.control import FAULT_NAMES
except ImportError:  # pragma: no cover - older engine
    FAULT_NAMES = {}

TWO_PI = 2.0 * math.pi


class Stamp:
    """t_k = k Ts as (sec, nanosec)."""

    def __init__(self, ts_s: float):
        self.ts_ns = int(round(ts_s * 1e9))

    def __call__(self, k: int) -> tuple[int, int]:
        return divmod(k * self.ts_ns, 1_000_000_000)


# ------------------------------------------------------------------------ PhaseFrame
class FrameWire:
    def __init__(self, frame_id: str = "", extra_flags: int = 0):
        self.codec = Codec(topics.T_FRAME, {"header.frame_id": frame_id})
        self.decoder = Decoder(topics.T_FRAME)
        self.extra_flags = extra_flags

    def pack(self, fr: np.ndarray, sec: int, nsec: int, extra_flags: int = 0) -> bytes:
        v = fr.tolist()
        return self.codec.pack(sec, nsec, int(v[FR_SEQ]), *v[0:10], v[FR_EN] > 0.5, v[FR_ENC],
                               int(v[FR_FLAGS]) | self.extra_flags | extra_flags)

    def unpack(self, data: bytes, out: np.ndarray) -> int:
        """Fill an FR_* row; returns seq."""
        v = self.decoder.decode(data)
        out[0:10] = v[3:13]
        out[FR_EN] = 1.0 if v[13] else 0.0
        out[FR_ENC] = v[14]
        out[FR_SEQ] = v[2]
        out[FR_FLAGS] = v[15] & FLAG_CLIP
        return v[2]


def frame_row(v: tuple) -> np.ndarray:
    """FR_* row from decoded PhaseFrame values (bag readers)."""
    out = np.zeros(FR_N)
    out[0:10] = v[3:13]
    out[FR_EN] = 1.0 if v[13] else 0.0
    out[FR_ENC] = v[14]
    out[FR_SEQ] = v[2]
    out[FR_FLAGS] = v[15] & FLAG_CLIP
    return out


# ------------------------------------------------------------------------ PlantTruth
# theta_e goes out as the engine has it, in [0, 2 pi) (as fluxdrive.io.bagio writes it too), so
# a graph bag and an in-process bag of the same run hold the same numbers.
class TruthWire:
    def __init__(self, frame_id: str = ""):
        self.codec = Codec(topics.T_TRUTH, {"header.frame_id": frame_id})
        self.decoder = Decoder(topics.T_TRUTH)

    def pack(self, tr: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        v = tr.tolist()
        return self.codec.pack(sec, nsec, seq, v[TR_THETA_E], v[TR_WM], v[TR_TE],
                               v[TR_TL], v[TR_IA], v[TR_IB], v[TR_IC])


def truth_row(v: tuple, ts_s: float) -> np.ndarray:
    out = np.zeros(TR_N)
    th = v[3]
    out[TR_THETA_E] = th + TWO_PI if th < 0.0 else th  # a bag following the msg comment
    out[TR_WM], out[TR_TE], out[TR_TL] = v[4], v[5], v[6]
    out[TR_IA], out[TR_IB], out[TR_IC] = v[7], v[8], v[9]
    out[TR_T] = v[2] * ts_s
    return out


# ------------------------------------------------------------------------ RotorEstimate
class EstimateWire:
    def __init__(self, variant: str, frame_id: str = ""):
        self.codec = Codec(topics.T_ESTIMATE, {"header.frame_id": frame_id, "variant": variant})
        self.decoder = Decoder(topics.T_ESTIMATE)

    def pack(self, es: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        v = es.tolist()
        return self.codec.pack(sec, nsec, seq, *v[0:7], v[ES_VALID] > 0.5)

    def unpack(self, data: bytes, out: np.ndarray) -> int:
        v = self.decoder.decode(data)
        out[0:7] = v[3:10]
        out[ES_VALID] = 1.0 if v[10] else 0.0
        return v[2]


def estimate_row(v: tuple) -> np.ndarray:
    out = np.zeros(ES_N)
    out[0:7] = v[3:10]
    out[ES_VALID] = 1.0 if v[10] else 0.0
    return out


# ------------------------------------------------------------- DutyCommand, ControllerState
class ControlWire:
    def __init__(self, frame_id: str = "", duty_frame_id: str | None = None):
        # duty_frame_id: the commanding node's mark (fluxdrive_ros.access), else frame_id
        self.duty = Codec(topics.T_DUTY, {"header.frame_id": frame_id if duty_frame_id is None
                                          else duty_frame_id})
        self.duty_decoder = Decoder(topics.T_DUTY)
        self.state_codecs: dict[int, Codec] = {}
        self.frame_id = frame_id

    def pack_duty(self, co: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        return self.duty.pack(sec, nsec, seq, float(co[CO_DA]), float(co[CO_DB]),
                              float(co[CO_DC]), bool(co[CO_EN] > 0.5))

    def pack_state(self, co: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        v = co.tolist()
        code = int(v[CO_FAULT])
        c = self.state_codecs.get(code)
        if c is None:
            # "<text>: fault code N" (fluxdrive.io.bagio.ctrl_row reads the trailing number)
            reason = "" if code == 0 else f"{FAULT_NAMES.get(code, 'fault')}: fault code {code}"
            c = Codec(topics.T_STATE, {"header.frame_id": self.frame_id, "fault_reason": reason})
            self.state_codecs[code] = c
        return c.pack(sec, nsec, seq, v[CO_ID], v[CO_IQ], v[CO_ID_REF], v[CO_IQ_REF], v[CO_VD],
                      v[CO_VQ], v[CO_W_REF], v[CO_W_FB], v[CO_TH], int(v[CO_MODE]))


def fault_code(reason: str) -> int:
    """ControllerState.fault_reason -> fluxdrive.drive.control fault code (-1: unknown)."""
    if not reason:
        return 0
    tail = reason.rsplit(" ", 1)[-1]
    return int(tail) if tail.isdigit() else -1


def control_row(duty_v: tuple | None, state_v: tuple | None, fault: int = 0) -> np.ndarray:
    """CO_* row from decoded DutyCommand and ControllerState values."""
    out = np.zeros(CO_N)
    if duty_v is not None:
        out[CO_DA], out[CO_DB], out[CO_DC] = duty_v[3], duty_v[4], duty_v[5]
        out[CO_EN] = 1.0 if duty_v[6] else 0.0
    if state_v is not None:
        (out[CO_ID], out[CO_IQ], out[CO_ID_REF], out[CO_IQ_REF], out[CO_VD], out[CO_VQ],
         out[CO_W_REF], out[CO_W_FB], out[CO_TH]) = state_v[3:12]
        out[CO_MODE] = state_v[12]
    out[CO_FAULT] = fault
    return out
