"""The CAN wire protocol's codec: message IDs, the engine frame's columns on the bus, the
DBC loaded with cantools, and a vectorised numpy fast path over it. No ROS imports.

The engine's per-period *frame* is a float64 row with the columns of
:data:`FRAME_FIELDS`: ``i_a, i_b, i_c`` [A], ``v_ab, v_bc, v_ca`` [V] (line voltages
averaged over the period that just ended), ``vdc`` [V], ``duty_a, duty_b, duty_c``
(0..1, applied over the period that just ended), ``pwm_enabled`` (0/1),
``encoder_counts`` [counts], ``seq`` (PWM-period counter) and ``flags`` (status bits,
bit 0 = current ADC clipped). The column order mirrors ``fluxdrive.drive.plant``'s ``FR_*``
indices. Timing as docs/engine.md (timing convention).

The numpy codec (:class:`NumpyCodec`) is generated from a cantools ``Message``: each
signal's start bit, length, byte order, signedness, float flag, scale and offset are
turned into an unaligned 64-bit load plus shift and mask. It decodes an ``(N, L)``
``uint8`` array of payloads in one vectorised call and agrees bit-exactly with cantools
(same IEEE operations: ``raw * scale + offset`` to decode, ``round((x - offset) / scale)``
with round-half-even to encode).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cantools
import numpy as np
from cantools.database.can import Database, Message

from fluxdrive.can.protocol.sequence import SEQ_BITS, unwrap_counter
from fluxdrive.core.paths import DBC_PATH
from fluxdrive.core.protocol_constants import (
    ID_SAMPLE_C_AUX,
    ID_SAMPLE_C_CUR,
    ID_SAMPLE_C_DUTY,
    ID_SAMPLE_C_VLT,
)
from fluxdrive.drive import plant as _pl

DBC_ENV_VAR = "FLUXDRIVE_DBC"
"""Environment variable overriding the DBC path."""

CLASSIC_SAMPLE_IDS = (ID_SAMPLE_C_CUR, ID_SAMPLE_C_VLT, ID_SAMPLE_C_DUTY, ID_SAMPLE_C_AUX)

FRAME_FIELDS: tuple[str, ...] = _pl.FRAME_COLUMNS
"""Column names of the engine's per-period frame row (float64), in the order of the
plant's ``FR_*`` indices: the names the plant's layout declares."""
FRAME_FLAG_ADC_CLIP = 1
"""Bit of the frame's ``flags`` column: a current ADC channel clipped (SAMPLE_FD.adc_clip)."""
FRAME_INDEX: dict[str, int] = {name: i for i, name in enumerate(FRAME_FIELDS)}

# SAMPLE_FD signal -> engine frame column
_FD_TO_FRAME: dict[str, str] = {
    "i_a": "i_a", "i_b": "i_b", "i_c": "i_c",
    "v_ab": "v_ab", "v_bc": "v_bc", "v_ca": "v_ca",
    "vdc": "vdc",
    "duty_a": "duty_a", "duty_b": "duty_b", "duty_c": "duty_c",
    "encoder": "encoder_counts", "pwm_enabled": "pwm_enabled", "seq": "seq",
    "adc_clip": "flags",
}  # fmt: skip
# classic-layout signal -> engine frame column, per message ID
_CLASSIC_TO_FRAME: dict[int, dict[str, str]] = {
    ID_SAMPLE_C_CUR: {"c_i_a": "i_a", "c_i_b": "i_b", "c_i_c": "i_c"},
    ID_SAMPLE_C_VLT: {"c_v_ab": "v_ab", "c_v_bc": "v_bc", "c_v_ca": "v_ca"},
    ID_SAMPLE_C_DUTY: {"c_duty_a": "duty_a", "c_duty_b": "duty_b", "c_duty_c": "duty_c"},
    ID_SAMPLE_C_AUX: {"c_vdc": "vdc", "c_encoder": "encoder_counts",
                      "c_pwm_enabled": "pwm_enabled", "c_adc_clip": "flags"},
}  # fmt: skip


# --------------------------------------------------------------------------- loading


def default_dbc_path() -> Path:
    """Path of the protocol DBC: ``$FLUXDRIVE_DBC`` if set, else the checkout's
    ``config/can/fluxdrive.dbc`` (fluxdrive.core.paths)."""
    env = os.environ.get(DBC_ENV_VAR)
    if env:
        return Path(env)
    return DBC_PATH


def load_database(path: str | os.PathLike[str] | None = None) -> Database:
    """Load the protocol DBC with cantools (strict). ``path`` overrides the default."""
    p = Path(path) if path is not None else default_dbc_path()
    if not p.is_file():
        raise FileNotFoundError(
            f"fluxdrive DBC not found at {p}; pass a path or set ${DBC_ENV_VAR}"
        )
    db = cantools.database.load_file(str(p), database_format="dbc", strict=True)
    assert isinstance(db, Database)
    return db


# --------------------------------------------------------------------------- numpy codec


@dataclass(frozen=True)
class _FieldSpec:
    """Bit layout of one signal as an unaligned 64-bit word load + shift + mask."""

    name: str
    byte_offset: int  # first byte of the 8-byte word that holds the signal
    shift: int  # right shift of the word to bring the signal's LSB to bit 0
    length: int  # bits
    signed: bool
    big_endian: bool
    is_float: bool
    scale: float
    offset: float
    minimum: float | None
    maximum: float | None
    range_check: bool  # False if every raw value lies within [minimum, maximum]


def _field_spec(sig: Any, msg_length: int) -> _FieldSpec:
    n = int(sig.length)
    if sig.byte_order == "little_endian":
        lsb = int(sig.start)  # DBC Intel start bit = LSB, bit i = byte i//8, bit i%8
        first = lsb // 8
        last = (lsb + n - 1) // 8
        shift = lsb - 8 * first
    else:
        # DBC Motorola start bit = MSB in sawtooth numbering; go to linear big-endian
        # numbering (bit 0 = MSB of byte 0) where the signal is contiguous.
        msb_lin = 8 * (sig.start // 8) + (7 - sig.start % 8)
        first = msb_lin // 8
        last = (msb_lin + n - 1) // 8
        # word = bytes[first:first+8] read big-endian; signal LSB sits at linear
        # position msb_lin+n-1, i.e. 63 - (msb_lin+n-1 - 8*first) from the word's bit 0.
        shift = 64 - (msb_lin + n - 8 * first)
    if last >= msg_length:
        raise ValueError(f"signal {sig.name} extends past the {msg_length}-byte payload")
    if shift < 0 or shift + n > 64:
        raise NotImplementedError(
            f"signal {sig.name}: {n} bits at this bit offset span more than 8 bytes"
        )
    if sig.is_float and n not in (32, 64):
        raise NotImplementedError(f"float signal {sig.name} must be 32 or 64 bits")
    scale = float(sig.scale)
    offset = float(sig.offset)
    mn = None if sig.minimum is None else float(sig.minimum)
    mx = None if sig.maximum is None else float(sig.maximum)
    if sig.is_float:
        range_check = mn is not None or mx is not None
    else:
        rlo, rhi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if sig.is_signed else (0, (1 << n) - 1)
        plo, phi = sorted((rlo * scale + offset, rhi * scale + offset))
        tol = 0.25 * abs(scale)
        range_check = (mn is not None and plo < mn - tol) or (mx is not None and phi > mx + tol)
    return _FieldSpec(
        name=sig.name,
        byte_offset=first,
        shift=shift,
        length=n,
        signed=bool(sig.is_signed),
        big_endian=sig.byte_order != "little_endian",
        is_float=bool(sig.is_float),
        scale=scale,
        offset=offset,
        minimum=mn,
        maximum=mx,
        range_check=bool(range_check),
    )


@dataclass
class ValidationReport:
    """Per-frame validity: ``valid[i]`` is False when frame i must be dropped, and
    ``reasons[i]`` says why (empty string for valid frames)."""

    valid: np.ndarray
    reasons: list[str]

    @property
    def n_valid(self) -> int:
        """Number of valid frames."""
        return int(np.count_nonzero(self.valid))

    @property
    def n_invalid(self) -> int:
        """Number of invalid (malformed) frames."""
        return int(self.valid.size - np.count_nonzero(self.valid))

    def invalid_reasons(self) -> dict[int, str]:
        """Map of frame index -> reason for the invalid frames only."""
        return {int(i): self.reasons[int(i)] for i in np.flatnonzero(~self.valid)}


@dataclass
class DecodeResult:
    """Decoded signals (``values``: (N, n_signals) float64, columns ``names``; rows of
    wrong-length frames are NaN) and the per-frame :class:`ValidationReport`."""

    values: np.ndarray
    names: tuple[str, ...]
    report: ValidationReport

    def column(self, name: str) -> np.ndarray:
        """One signal's column by name."""
        return self.values[:, self.names.index(name)]


def pack_payloads(
    datas: Sequence[bytes | bytearray | memoryview], length: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pack variable-length payloads into an ``(N, length)`` uint8 array (zero padded or
    truncated) plus the ``(N,)`` array of actual lengths (for DLC checks)."""
    n = len(datas)
    lens = np.fromiter((len(d) for d in datas), dtype=np.int64, count=n)
    if n and bool(np.all(lens == length)):
        arr = np.frombuffer(b"".join(bytes(d) for d in datas), dtype=np.uint8)
        return arr.reshape(n, length).copy(), lens
    arr = np.zeros((n, length), dtype=np.uint8)
    for i, d in enumerate(datas):
        b = bytes(d)[:length]
        arr[i, : len(b)] = np.frombuffer(b, dtype=np.uint8)
    return arr, lens


class NumpyCodec:
    """Vectorised encoder/decoder for one DBC message, generated from its signals.

    ``decode(payloads)`` maps an ``(N, L)`` uint8 array to ``(N, n_signals)`` float64
    physical values (units as in the DBC); ``encode(values)`` is the inverse. Results
    are bit-identical to cantools' ``decode(..., decode_choices=False)`` and
    ``encode(..., scaling=True)``.
    """

    def __init__(self, message: Message) -> None:
        self.message = message
        self.length: int = int(message.length)
        self.specs: tuple[_FieldSpec, ...] = tuple(
            _field_spec(s, self.length) for s in message.signals
        )
        self.names: tuple[str, ...] = tuple(s.name for s in self.specs)
        self.index: dict[str, int] = {n: i for i, n in enumerate(self.names)}

    # -- raw access ------------------------------------------------------------------

    def _padded(self, payloads: np.ndarray) -> np.ndarray:
        p = np.asarray(payloads)
        if p.dtype != np.uint8 or p.ndim != 2 or p.shape[1] != self.length:
            raise ValueError(
                f"{self.message.name}: expected (N, {self.length}) uint8 payloads, "
                f"got {p.shape} {p.dtype}"
            )
        buf = np.zeros((p.shape[0], self.length + 8), dtype=np.uint8)
        buf[:, : self.length] = p
        return buf

    @staticmethod
    def _word_view(buf: np.ndarray, spec: _FieldSpec) -> np.ndarray:
        """Unaligned (N,) uint64 view of 8 bytes at the spec's byte offset in each row."""
        return np.ndarray(
            shape=(buf.shape[0],),
            dtype=np.dtype(">u8" if spec.big_endian else "<u8"),
            buffer=buf,
            offset=spec.byte_offset,
            strides=(buf.strides[0],),
        )

    def decode_raw(self, payloads: np.ndarray, names: Sequence[str] | None = None) -> np.ndarray:
        """Raw integer signal values, ``(N, k)`` int64 (float signals: their bit pattern)."""
        buf = self._padded(payloads)
        specs = self._select(names)
        out = np.empty((buf.shape[0], len(specs)), dtype=np.int64)
        for j, sp in enumerate(specs):
            out[:, j] = self._extract(buf, sp).view(np.int64)
        return out

    def _extract(self, buf: np.ndarray, sp: _FieldSpec) -> np.ndarray:
        word = self._word_view(buf, sp)
        mask = np.uint64((1 << sp.length) - 1)
        raw = (word >> np.uint64(sp.shift)) & mask
        if sp.signed and not sp.is_float and sp.length < 64:
            sign = np.uint64(1 << (sp.length - 1))
            ext = (raw ^ sign).view(np.int64) - np.int64(1 << (sp.length - 1))
            return ext.view(np.uint64)
        return raw

    def _select(self, names: Sequence[str] | None) -> tuple[_FieldSpec, ...]:
        if names is None:
            return self.specs
        return tuple(self.specs[self.index[n]] for n in names)

    # -- physical values -------------------------------------------------------------

    def decode(self, payloads: np.ndarray, names: Sequence[str] | None = None) -> np.ndarray:
        """Decode ``(N, L)`` uint8 payloads to ``(N, k)`` float64 physical values."""
        buf = self._padded(payloads)
        specs = self._select(names)
        out = np.empty((buf.shape[0], len(specs)), dtype=np.float64)
        for j, sp in enumerate(specs):
            raw = self._extract(buf, sp)
            if sp.is_float:
                if sp.length == 32:
                    val = raw.astype(np.uint32).view(np.float32).astype(np.float64)
                else:
                    val = raw.view(np.float64)
            elif sp.signed:
                val = raw.view(np.int64).astype(np.float64)
            else:
                val = raw.astype(np.float64)
            if sp.scale != 1.0 or sp.offset != 0.0:
                val = val * sp.scale + sp.offset
            out[:, j] = val
        return out

    def to_raw(self, values: np.ndarray) -> np.ndarray:
        """Physical ``(N, n_signals)`` values -> raw integers (int64; float signals: bit
        pattern), rounding half to even like cantools. No range check."""
        v = np.asarray(values, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != len(self.specs):
            raise ValueError(f"expected (N, {len(self.specs)}) values, got {v.shape}")
        raw = np.empty(v.shape, dtype=np.int64)
        for j, sp in enumerate(self.specs):
            col = v[:, j]
            if sp.is_float:
                x = col if sp.scale == 1.0 and sp.offset == 0.0 else (col - sp.offset) / sp.scale
                if sp.length == 32:
                    raw[:, j] = x.astype(np.float32).view(np.uint32).astype(np.int64)
                else:
                    raw[:, j] = x.view(np.int64)
            else:
                x = col if sp.scale == 1.0 and sp.offset == 0.0 else (col - sp.offset) / sp.scale
                raw[:, j] = np.rint(x).astype(np.int64)
        return raw

    def encode_raw(self, raw: np.ndarray) -> np.ndarray:
        """Pack ``(N, n_signals)`` raw integers into ``(N, L)`` uint8 payloads. Raw values
        are reduced to their bit width (two's complement), i.e. they wrap."""
        r = np.asarray(raw, dtype=np.int64)
        n = r.shape[0]
        buf = np.zeros((n, self.length + 8), dtype=np.uint8)
        for j, sp in enumerate(self.specs):
            mask = np.uint64((1 << sp.length) - 1)
            word = (r[:, j].view(np.uint64) & mask) << np.uint64(sp.shift)
            view = self._word_view(buf, sp)
            view |= word
        return buf[:, : self.length].copy()

    def encode(self, values: np.ndarray, *, check: bool = True) -> np.ndarray:
        """Encode ``(N, n_signals)`` physical values to ``(N, L)`` uint8 payloads.

        With ``check`` (default) any NaN/inf or out-of-range value raises ``ValueError``
        naming the offending rows; use :meth:`validate_values` to get a mask instead."""
        if check:
            rep = self.validate_values(values)
            if rep.n_invalid:
                bad = rep.invalid_reasons()
                head = "; ".join(f"row {i}: {r}" for i, r in list(bad.items())[:5])
                raise ValueError(f"{self.message.name}: {len(bad)} invalid rows: {head}")
        return self.encode_raw(self.to_raw(values))

    # -- validation ------------------------------------------------------------------

    def _range_flags(self, values: np.ndarray, check_all: bool) -> list[tuple[int, np.ndarray]]:
        flags = []
        for j, sp in enumerate(self.specs):
            if not (sp.range_check or check_all):
                continue
            col = values[:, j]
            tol = 0.0 if sp.is_float else 0.25 * abs(sp.scale)
            bad = np.zeros(col.shape, dtype=bool)
            if sp.minimum is not None:
                bad |= col < sp.minimum - tol
            if sp.maximum is not None:
                bad |= col > sp.maximum + tol
            if bad.any():
                flags.append((j, bad))
        return flags

    # -- one frame at a time (cantools underneath: ~100x less overhead than an (1, L) array)

    def _row_reason(self, vals: Sequence[float], check_all: bool) -> str:
        msgs = []
        for sp, v in zip(self.specs, vals, strict=True):
            if not math.isfinite(v):
                msgs.append(f"{sp.name} is {v}")
                continue
            if not (sp.range_check or check_all):
                continue
            tol = 0.0 if sp.is_float else 0.25 * abs(sp.scale)
            if (sp.minimum is not None and v < sp.minimum - tol) or (
                sp.maximum is not None and v > sp.maximum + tol
            ):
                msgs.append(f"{sp.name}={v:g} outside [{sp.minimum:g}, {sp.maximum:g}]")
        return "; ".join(msgs)

    def decode_one(self, data: bytes | bytearray | memoryview) -> tuple[np.ndarray | None, str]:
        """Checked decode of one payload: ``(values in names order, "")``, or
        ``(None, reason)`` for a frame :meth:`decode_checked` would flag (same values,
        same checks, same reasons)."""
        b = bytes(data)
        if len(b) != self.length:
            return None, f"wrong length {len(b)} bytes (expected {self.length})"
        d = self.message.decode(b, decode_choices=False, scaling=True)
        vals = [float(d[n]) for n in self.names]  # type: ignore[index]
        reason = self._row_reason(vals, check_all=False)
        return (None, reason) if reason else (np.array(vals), "")

    def encode_one(self, values: Mapping[str, float]) -> bytes:
        """Encode one frame from ``{signal: physical value}`` (missing signals 0) with the
        checks of :meth:`encode` (finite, within the DBC range); same bytes."""
        vals = [float(values.get(n, 0.0)) for n in self.names]
        reason = self._row_reason(vals, check_all=True)
        if reason:
            raise ValueError(f"{self.message.name}: invalid values: {reason}")
        return bytes(self.message.encode(dict(zip(self.names, vals, strict=True)), strict=False))

    def validate_values(self, values: np.ndarray) -> ValidationReport:
        """Check physical values before encoding: finite and within the DBC [min, max]
        (plus a quarter LSB of tolerance for integer signals)."""
        v = np.asarray(values, dtype=np.float64)
        n = v.shape[0]
        valid = np.ones(n, dtype=bool)
        reasons = [""] * n
        notfinite = ~np.isfinite(v)
        with np.errstate(invalid="ignore"):
            flags = self._range_flags(v, check_all=True)
        bad_rows = notfinite.any(axis=1)
        for _, b in flags:
            bad_rows |= b
        for i in np.flatnonzero(bad_rows):
            msgs = [f"{self.names[j]} is {v[i, j]}" for j in np.flatnonzero(notfinite[i])]
            msgs += [
                f"{self.names[j]}={v[i, j]:g} outside [{self.specs[j].minimum:g}, "
                f"{self.specs[j].maximum:g}]"
                for j, b in flags
                if b[i] and np.isfinite(v[i, j])
            ]
            reasons[int(i)] = "; ".join(msgs)
        valid &= ~bad_rows
        return ValidationReport(valid=valid, reasons=reasons)

    def decode_checked(
        self,
        payloads: np.ndarray | Sequence[bytes | bytearray | memoryview],
        lengths: np.ndarray | None = None,
        names: Sequence[str] | None = None,
    ) -> DecodeResult:
        """Decode and validate received payloads; never raises on bad frame content.

        ``payloads`` is an ``(N, L)`` uint8 array (then ``lengths`` optionally gives each
        frame's real DLC in bytes) or a sequence of byte strings of any length. A frame is
        invalid when its length is not L, a decoded value lies outside the DBC [min, max],
        or a float signal is NaN/inf. Invalid rows are flagged in the report; rows with a
        wrong length are set to NaN."""
        if isinstance(payloads, np.ndarray):
            arr = payloads
            lens = (
                np.full(arr.shape[0], self.length, dtype=np.int64)
                if lengths is None
                else np.asarray(lengths, dtype=np.int64)
            )
        else:
            arr, lens = pack_payloads(payloads, self.length)
        full = self.decode(arr)
        n = full.shape[0]
        valid = np.ones(n, dtype=bool)
        reasons = [""] * n
        badlen = lens != self.length
        notfinite = ~np.isfinite(full)
        with np.errstate(invalid="ignore"):
            flags = self._range_flags(full, check_all=False)
        bad_rows = badlen | notfinite.any(axis=1)
        for _, b in flags:
            bad_rows |= b
        for i in np.flatnonzero(bad_rows):
            if badlen[i]:
                reasons[int(i)] = f"wrong length {int(lens[i])} bytes (expected {self.length})"
                continue
            msgs = [f"{self.names[j]} is {full[i, j]}" for j in np.flatnonzero(notfinite[i])]
            msgs += [
                f"{self.names[j]}={full[i, j]:g} outside [{self.specs[j].minimum:g}, "
                f"{self.specs[j].maximum:g}]"
                for j, b in flags
                if b[i] and np.isfinite(full[i, j])
            ]
            reasons[int(i)] = "; ".join(msgs)
        valid &= ~bad_rows
        full[badlen] = np.nan
        sel = self.names if names is None else tuple(names)
        values = full if names is None else full[:, [self.index[s] for s in sel]]
        return DecodeResult(values=values, names=sel, report=ValidationReport(valid, reasons))


# --------------------------------------------------------------------------- protocol


class FluxdriveProtocol:
    """The loaded DBC plus convenience encode/decode (cantools) and the numpy fast
    path for SAMPLE_FD. Use :func:`get_protocol` for a cached default instance."""

    def __init__(self, dbc_path: str | os.PathLike[str] | None = None) -> None:
        self.db: Database = load_database(dbc_path)
        self.messages: dict[str, Message] = {m.name: m for m in self.db.messages}
        self.sample_fd: Message = self.messages["SAMPLE_FD"]
        self.fd_codec = NumpyCodec(self.sample_fd)
        self.classic_codecs: dict[int, NumpyCodec] = {
            fid: NumpyCodec(self.db.get_message_by_frame_id(fid)) for fid in CLASSIC_SAMPLE_IDS
        }
        attrs = self.db.dbc.attributes if self.db.dbc is not None else {}
        self.classic_decimation: int = int(attrs["ClassicDecimation"].value)
        self.fd_decimation: int = int(attrs["FdDecimation"].value)
        """FD layout's default D (1: a SAMPLE_FD every PWM period, virtual bus / bench PC)."""
        self.fd_decimation_real_bus: int = int(attrs["FdDecimationRealBus"].value)
        """Smallest FD-layout D that fits a real 1/5 Mbit/s bus (:func:`link_budget`)."""
        self.protocol_version: int = int(attrs["ProtocolVersion"].value)
        self.pwm_frequency: float = float(attrs["PwmFrequency"].value)
        self._fd_cols = [self.fd_codec.index[s] for s in _FD_TO_FRAME]
        self._fd_frame_cols = [FRAME_INDEX[c] for c in _FD_TO_FRAME.values()]

    def default_decimation(self, layout: str) -> int:
        """The DBC's default D of a sample layout ("fd": FdDecimation, "classic":
        ClassicDecimation)."""
        if layout not in ("fd", "classic"):
            raise ValueError(f"layout must be 'fd' or 'classic', not {layout!r}")
        return self.fd_decimation if layout == "fd" else self.classic_decimation

    def message(self, name_or_id: str | int) -> Message:
        """Message by name or arbitration ID."""
        if isinstance(name_or_id, int):
            return self.db.get_message_by_frame_id(name_or_id)
        return self.messages[name_or_id]

    def encode(self, name_or_id: str | int, signals: Mapping[str, Any], **kw: Any) -> bytes:
        """Encode one message with cantools (strict range check, scaling); missing
        signals default to 0."""
        msg = self.message(name_or_id)
        data = {s.name: 0 for s in msg.signals}
        data.update(signals)
        return bytes(msg.encode(data, **kw))

    def decode(
        self, name_or_id: str | int, data: bytes | bytearray, *, decode_choices: bool = False
    ) -> dict[str, Any]:
        """Decode one message with cantools (raises on a wrong length)."""
        out = self.message(name_or_id).decode(bytes(data), decode_choices=decode_choices)
        assert isinstance(out, dict)  # not a container message
        return out

    # -- engine frames <-> SAMPLE_FD ---------------------------------------------------

    def frames_to_signal_values(
        self, frames: np.ndarray, extra: Mapping[str, float | np.ndarray] | None = None
    ) -> np.ndarray:
        """Engine frame rows -> SAMPLE_FD physical signal matrix (seq wrapped to 16 bit,
        encoder wrapped to int32); ``extra`` sets the other signals (default 0)."""
        f = np.atleast_2d(np.asarray(frames, dtype=np.float64))
        if f.shape[1] != len(FRAME_FIELDS):
            raise ValueError(f"frame rows must have {len(FRAME_FIELDS)} columns, got {f.shape}")
        vals = np.zeros((f.shape[0], len(self.fd_codec.names)), dtype=np.float64)
        vals[:, self._fd_cols] = f[:, self._fd_frame_cols]
        with np.errstate(invalid="ignore"):
            seq = f[:, FRAME_INDEX["seq"]]
            enc = f[:, FRAME_INDEX["encoder_counts"]]
            ok = np.isfinite(seq)
            vals[ok, self.fd_codec.index["seq"]] = np.mod(np.rint(seq[ok]), 1 << SEQ_BITS)
            ok = np.isfinite(enc)
            vals[ok, self.fd_codec.index["encoder"]] = (
                np.mod(np.rint(enc[ok]) + 2**31, 2**32) - 2**31
            )
            flg = f[:, FRAME_INDEX["flags"]]
            ok = np.isfinite(flg)
            vals[ok, self.fd_codec.index["adc_clip"]] = (
                flg[ok].astype(np.int64) & FRAME_FLAG_ADC_CLIP
            )
        for k, v in (extra or {}).items():
            vals[:, self.fd_codec.index[k]] = v
        return vals

    def frames_to_fd_payloads(
        self,
        frames: np.ndarray,
        extra: Mapping[str, float | np.ndarray] | None = None,
        *,
        check: bool = True,
    ) -> np.ndarray:
        """Engine frames (N, 14) -> (N, 64) uint8 SAMPLE_FD payloads (vectorised)."""
        return self.fd_codec.encode(self.frames_to_signal_values(frames, extra), check=check)

    def fd_payloads_to_frames(self, payloads: np.ndarray) -> np.ndarray:
        """(N, 64) uint8 SAMPLE_FD payloads -> engine frames (N, 14) float64 (no checks;
        use :meth:`decode_fd` for validation)."""
        vals = self.fd_codec.decode(payloads)
        return self._fd_values_to_frames(vals)

    def _fd_values_to_frames(self, vals: np.ndarray) -> np.ndarray:
        out = np.empty((vals.shape[0], len(FRAME_FIELDS)), dtype=np.float64)
        out[:, self._fd_frame_cols] = vals[:, self._fd_cols]
        return out

    def decode_fd(
        self,
        payloads: np.ndarray | Sequence[bytes | bytearray | memoryview],
        lengths: np.ndarray | None = None,
    ) -> tuple[np.ndarray, DecodeResult]:
        """Checked decode of SAMPLE_FD payloads: (engine frames, full DecodeResult)."""
        res = self.fd_codec.decode_checked(payloads, lengths)
        return self._fd_values_to_frames(res.values), res

    # -- classic layout ----------------------------------------------------------------

    def frame_to_classic_payloads(
        self, frame: np.ndarray, flags: Mapping[str, float] | None = None
    ) -> list[tuple[int, bytes]]:
        """One engine frame (already decimated, see :func:`decimate_frames`) -> the
        four classic frames [(id, 8-byte payload)] in send order CUR, VLT, DUTY, AUX.
        The encoder is sent as its low 24 bits; ``flags`` sets the AUX flag bits."""
        f = np.asarray(frame, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(f)):
            raise ValueError("classic sample: non-finite values in the frame")
        seq = int(np.rint(f[FRAME_INDEX["seq"]])) % (1 << SEQ_BITS)
        out: list[tuple[int, bytes]] = []
        for fid in CLASSIC_SAMPLE_IDS:
            codec = self.classic_codecs[fid]
            vals: dict[str, float] = {"c_seq": seq}
            for sig, col in _CLASSIC_TO_FRAME[fid].items():
                v = float(f[FRAME_INDEX[col]])
                if sig == "c_encoder":
                    v = float((int(np.rint(v)) + (1 << 23)) % (1 << 24) - (1 << 23))
                elif sig == "c_adc_clip":
                    v = float(int(v) & FRAME_FLAG_ADC_CLIP)
                vals[sig] = v
            if fid == ID_SAMPLE_C_AUX:
                vals.update({k: float(v) for k, v in (flags or {}).items()})
            out.append((fid, codec.encode_one(vals)))
        return out


_DEFAULT: dict[str, FluxdriveProtocol] = {}


def get_protocol(dbc_path: str | os.PathLike[str] | None = None) -> FluxdriveProtocol:
    """Cached :class:`FluxdriveProtocol` for ``dbc_path`` (default DBC if None)."""
    key = str(Path(dbc_path).resolve()) if dbc_path is not None else str(default_dbc_path())
    if key not in _DEFAULT:
        _DEFAULT[key] = FluxdriveProtocol(dbc_path)
    return _DEFAULT[key]


def frame_to_fd_payload(
    frame: np.ndarray | Sequence[float],
    extra: Mapping[str, float] | None = None,
    *,
    protocol: FluxdriveProtocol | None = None,
) -> bytes:
    """One engine frame row (14 floats, :data:`FRAME_FIELDS`) -> 64-byte SAMPLE_FD
    payload. ``extra`` sets signals that are not in the frame (``cmd_seq_applied``,
    ``t_mcu`` [s], ``armed``, ``fault_active``, ``adc_clip``, ``cmd_stale``,
    ``capture_valid``, ``mode``, ``fault_code``). Raises ``ValueError`` on NaN or
    out-of-range values."""
    proto = protocol or get_protocol()
    row = np.asarray(frame, dtype=np.float64).reshape(1, -1)
    return proto.frames_to_fd_payloads(row, extra)[0].tobytes()


def frames_to_fd_payloads(
    frames: np.ndarray,
    extra: Mapping[str, float | np.ndarray] | None = None,
    *,
    check: bool = True,
    protocol: FluxdriveProtocol | None = None,
) -> np.ndarray:
    """Vectorised :func:`frame_to_fd_payload`: (N, 14) frames -> (N, 64) uint8."""
    return (protocol or get_protocol()).frames_to_fd_payloads(frames, extra, check=check)


def fd_payloads_to_frames(
    payloads: np.ndarray | Sequence[bytes | bytearray | memoryview],
    *,
    protocol: FluxdriveProtocol | None = None,
) -> np.ndarray:
    """SAMPLE_FD payloads ((N, 64) uint8 array, or a sequence of 64-byte strings) ->
    engine frames (N, 14) float64. Unchecked fast path; see
    :meth:`FluxdriveProtocol.decode_fd` for per-frame validation."""
    proto = protocol or get_protocol()
    if not isinstance(payloads, np.ndarray):
        payloads, lens = pack_payloads(payloads, proto.fd_codec.length)
        if np.any(lens != proto.fd_codec.length):
            raise ValueError("payloads of the wrong length; use decode_fd() to flag them")
    return proto.fd_payloads_to_frames(payloads)


def frame_to_classic_payloads(
    frame: np.ndarray | Sequence[float],
    flags: Mapping[str, float] | None = None,
    *,
    protocol: FluxdriveProtocol | None = None,
) -> list[tuple[int, bytes]]:
    """See :meth:`FluxdriveProtocol.frame_to_classic_payloads`."""
    return (protocol or get_protocol()).frame_to_classic_payloads(np.asarray(frame), flags)


def decimate_frames(frames: np.ndarray, factor: int) -> np.ndarray:
    """Per-period engine frames -> the decimated samples the MCU sends every ``factor``
    periods (either layout: ARM_MODE.decimation). Window j covers periods ``(j*D, (j+1)*D]``, i.e.
    rows ``j*D+1 .. (j+1)*D``; currents, vdc, encoder and seq are those of the last row;
    line voltages and duties are window means (volt-seconds over [t_(k-D), t_k]);
    pwm_enabled is 1 only if enabled in every period of the window; flags are OR-ed."""
    f = np.asarray(frames, dtype=np.float64)
    d = int(factor)
    if d < 1:
        raise ValueError("decimation factor must be >= 1")
    n_win = (f.shape[0] - 1) // d
    if n_win <= 0:
        return np.empty((0, f.shape[1]))
    body = f[1 : 1 + n_win * d].reshape(n_win, d, f.shape[1])
    out = body[:, -1, :].copy()
    for name in ("v_ab", "v_bc", "v_ca", "duty_a", "duty_b", "duty_c"):
        out[:, FRAME_INDEX[name]] = body[:, :, FRAME_INDEX[name]].mean(axis=1)
    out[:, FRAME_INDEX["pwm_enabled"]] = body[:, :, FRAME_INDEX["pwm_enabled"]].min(axis=1)
    flg = body[:, :, FRAME_INDEX["flags"]].astype(np.int64)
    out[:, FRAME_INDEX["flags"]] = np.bitwise_or.reduce(flg, axis=1)
    return out


decimate_for_classic = decimate_frames
"""The classic layout's name for :func:`decimate_frames` (same windows in both layouts)."""


# --------------------------------------------------------------------------- classic


@dataclass
class ClassicReassembler:
    """Reassemble classic-layout samples (SAMPLE_C_CUR/VLT/DUTY/AUX sharing c_seq) into
    engine frames. Feed every received classic sample frame to :meth:`feed`; a frame row
    is returned when all four parts of one seq have arrived. A part with a new seq
    before the previous set is complete drops that set (counted in ``incomplete``).
    Malformed parts (wrong length, out of range) are counted in ``malformed`` and
    ignored. The 24-bit encoder is unwrapped against the previous sample."""

    protocol: FluxdriveProtocol = field(default_factory=get_protocol)
    incomplete: int = 0
    malformed: int = 0
    completed: int = 0
    reasons: list[str] = field(default_factory=list)
    last_aux: dict[str, float] = field(default_factory=dict, init=False)
    """SAMPLE_C_AUX signals of the last completed sample (flags: c_armed, c_cmd_stale, ...)."""
    _seq: int | None = field(default=None, init=False, repr=False)
    _parts: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False)
    _enc_prev: float | None = field(default=None, init=False, repr=False)

    def feed(self, arbitration_id: int, data: bytes | bytearray) -> np.ndarray | None:
        """Accept one classic sample frame; return a completed (14,) frame or None."""
        codec = self.protocol.classic_codecs.get(arbitration_id)
        if codec is None:
            return None
        vals, reason = codec.decode_one(data)
        if vals is None:
            self.malformed += 1
            if len(self.reasons) < 100:
                self.reasons.append(f"0x{arbitration_id:03X}: {reason}")
            return None
        seq = int(vals[codec.index["c_seq"]])
        if self._seq is not None and seq != self._seq:
            if self._parts:
                self.incomplete += 1
            self._parts = {}
        self._seq = seq
        self._parts[arbitration_id] = vals
        if len(self._parts) < len(CLASSIC_SAMPLE_IDS):
            return None
        frame = np.zeros(len(FRAME_FIELDS), dtype=np.float64)
        for fid, part in self._parts.items():
            c = self.protocol.classic_codecs[fid]
            for sig, col in _CLASSIC_TO_FRAME[fid].items():
                frame[FRAME_INDEX[col]] = part[c.index[sig]]
        enc = unwrap_counter(
            np.array([frame[FRAME_INDEX["encoder_counts"]]]), 24, prev=self._enc_prev
        )[0]
        frame[FRAME_INDEX["encoder_counts"]] = enc
        self._enc_prev = enc
        frame[FRAME_INDEX["seq"]] = seq
        aux = self.protocol.classic_codecs[ID_SAMPLE_C_AUX]
        self.last_aux = dict(zip(aux.names, self._parts[ID_SAMPLE_C_AUX].tolist(), strict=True))
        self._parts = {}
        self._seq = None
        self.completed += 1
        return frame

    def feed_many(self, frames: Iterable[tuple[int, bytes | bytearray]]) -> np.ndarray:
        """Feed (id, payload) pairs; return the completed frames as (M, 14)."""
        rows = [r for fid, d in frames if (r := self.feed(fid, d)) is not None]
        if not rows:
            return np.empty((0, len(FRAME_FIELDS)))
        return np.vstack(rows)
