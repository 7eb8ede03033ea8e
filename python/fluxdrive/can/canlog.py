"""CAN log import core: candump ``.log``, Vector ``.asc``, ``.blf`` and PCAN ``.trc`` ->
numpy frames.

Reads a bench capture with python-can's readers (CAN FD frames survive in all four
formats: ``.trc`` from version 2.0 on, frame types FD/FB/FE/BI), picks the sample frames
by arbitration ID, decodes
them with the vectorised SAMPLE_FD codec (or reassembles the classic 4-frame layout)
and returns engine frames (:data:`fluxdrive.can.protocol.FRAME_FIELDS` columns) plus
counts. Writing a ROS bag from the result is the job of the ``can-import`` command.
No ROS imports.

Captures the project writes (``write_capture``, the CAN loop's tap: ``open_writer``)
follow the formats' specifications for CAN FD:

- candump ``.log``: ``(time) can0 123##<flags><data>`` -- ``##`` marks an FD frame, one hex
  digit of flags (BRS 1, ESI 2), then up to 64 data bytes (can-utils ``lib.h``,
  ``parse_canframe``); classic frames ``123#<data>``;
- ``.blf``: an FD frame is a CAN_FD_MESSAGE object (type 100) of the full size the format
  defines -- channel, flags, DLC code, id, frame length, bit count, FD flags (EDL 1, BRS 2,
  ESI 4), valid data bytes, reserved, 64 data bytes, and the trailing reserved DWORD
  python-can's writer leaves out (116 instead of 120 bytes; a reader walking the object
  by its declared fields then reads 4 bytes of the next object);
- ``.trc`` is read only: python-can's TRC writer drops FD frames.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from fluxdrive.can.protocol import (
    CLASSIC_SAMPLE_IDS,
    FRAME_FIELDS,
    ID_SAMPLE_FD,
    SEQ_BITS,
    ClassicReassembler,
    FluxdriveProtocol,
    SeqFilter,
    get_protocol,
    pack_payloads,
)
from fluxdrive.drive.plant import FR_SEQ

__all__ = [
    "SUPPORTED_SUFFIXES",
    "WRITE_SUFFIXES",
    "CaptureError",
    "CaptureResult",
    "open_writer",
    "read_capture",
    "write_capture",
]

SUPPORTED_SUFFIXES = (".log", ".asc", ".blf", ".trc")
"""Capture formats that keep CAN FD frames (read)."""
WRITE_SUFFIXES = (".log", ".asc", ".blf")
"""Capture formats written with CAN FD frames (python-can's .trc writer drops them)."""


@dataclass
class CaptureResult:
    """Decoded capture.

    ``frames``: (M, 14) float64 engine frames of the valid sample frames, in log order;
    ``timestamps``: (M,) log timestamps [s] (absolute, as stored); ``counts``:
    ``total`` (all messages in the log), ``sample`` (messages with a sample ID),
    ``decoded`` (valid samples),
    ``malformed`` (wrong length / out of range / wrong FD flag), ``other`` (non-sample
    messages), ``error_frames``, ``gaps`` / ``lost`` / ``duplicates`` / ``out_of_order``
    / ``jumps`` / ``resyncs`` / ``rejected`` (sequence counter over the decoded samples,
    :class:`fluxdrive.can.protocol.SeqFilter`: only new samples are kept -- a repeated or
    replayed, late or jumping sample is counted and left out of ``frames``), ``kept``
    (the samples in ``frames``); ``layout``: "fd", "classic" or "none";
    ``reasons``: up to 100 examples of why frames were rejected (index, reason);
    ``truncated``: why the capture ends early ("" if it does not; a .blf only)."""

    frames: np.ndarray
    timestamps: np.ndarray
    counts: dict[str, int]
    layout: str
    reasons: list[tuple[int, str]] = field(default_factory=list)
    bad_lines: list[tuple[int, str]] = field(default_factory=list)  # (line, why), first 20
    step: int = 1  # wire seq step between samples (the layout's decimation D)
    truncated: str = ""

    def column(self, name: str) -> np.ndarray:
        """One frame column by name (see FRAME_FIELDS)."""
        return self.frames[:, FRAME_FIELDS.index(name)]


def _check_suffix(path: Path, allowed: tuple[str, ...] = SUPPORTED_SUFFIXES) -> None:
    if path.suffix.lower() not in allowed:
        why = "" if ".trc" in allowed else "; python-can's .trc writer drops CAN FD frames"
        raise ValueError(
            f"{path.name}: unsupported capture format {path.suffix!r} "
            f"(use one of {', '.join(allowed)}{why})"
        )


class _BLFWriter(can.BLFWriter):
    """python-can's BLF writer with CAN FD frames as full-size CAN_FD_MESSAGE objects
    (the format's trailing reserved DWORD included, see the module notes), and every log
    container holding whole objects: python-can cuts its containers at a fixed size, so an
    object may continue in the next container -- the format allows it, but readers that
    walk each container on its own (SavvyCAN's) lose the frame at every cut."""

    def _add_object(self, obj_type: int, data: bytes, timestamp: float | None = None) -> None:
        size = 32 + len(data) + len(data) % 4  # V1 object header + body + python-can's padding
        if self._buffer_size and self._buffer_size + size > self.max_container_size:
            self._flush()  # the buffer holds whole objects only: one container, no tail
        super()._add_object(obj_type, data, timestamp)

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_fd or msg.is_error_frame:
            super().on_message_received(msg)
            return
        from can.io import blf

        channel = blf.channel2int(msg.channel)
        channel = self.channel if channel is None else channel + 1  # BLF counts from 1
        arb_id = msg.arbitration_id | (blf.CAN_MSG_EXT if msg.is_extended_id else 0)
        flags = (blf.REMOTE_FLAG if msg.is_remote_frame else 0) | (0 if msg.is_rx else blf.DIR)
        fd_flags = (
            blf.EDL
            | (blf.BRS if msg.bitrate_switch else 0)
            | (blf.ESI if msg.error_state_indicator else 0)
        )
        data = bytes(msg.data)
        body = blf.CAN_FD_MSG_STRUCT.pack(
            channel, flags, blf.len2dlc(len(data)), arb_id, 0, 0, fd_flags, len(data), data
        )
        self._add_object(blf.CAN_FD_MESSAGE, body + bytes(4), msg.timestamp)


def open_writer(path: str | os.PathLike[str]) -> can.io.generic.MessageWriter:
    """A capture writer for `path` (format from the suffix, as python-can's Logger): python-
    can's, with FD frames in .blf as the format defines them."""
    p = Path(path)
    if p.suffix.lower() == ".blf":
        return _BLFWriter(str(p))
    return can.Logger(str(p))


@dataclass
class _Sorted:
    """A capture's messages by kind: SAMPLE_FD payloads (with stamps and FD flags), classic
    sample parts, and counts of the rest."""

    total: int = 0
    other: int = 0
    errors: int = 0
    fd_data: list[bytes] = field(default_factory=list)
    fd_ts: list[float] = field(default_factory=list)
    fd_isfd: list[bool] = field(default_factory=list)
    classic: list[tuple[int, bytes, float]] = field(default_factory=list)
    foreign_ids: list[int] = field(default_factory=list)  # the first 3 other IDs seen


def _sort_messages(messages, sample_id: int, classic_ids: Sequence[int]) -> _Sorted:
    classic = set(classic_ids)
    got = _Sorted()
    for msg in messages:
        got.total += 1
        if msg.is_error_frame:
            got.errors += 1
            continue
        aid = msg.arbitration_id
        if aid == sample_id and not msg.is_extended_id:
            got.fd_data.append(bytes(msg.data))
            got.fd_ts.append(msg.timestamp)
            got.fd_isfd.append(bool(msg.is_fd))
        elif aid in classic and not msg.is_extended_id:
            got.classic.append((aid, bytes(msg.data), msg.timestamp))
        else:
            got.other += 1
            if len(got.foreign_ids) < 3 and aid not in got.foreign_ids:
                got.foreign_ids.append(aid)
    return got


def _samples_text(sample_id: int, classic_ids: Sequence[int]) -> str:
    return (
        f"SAMPLE_FD 0x{sample_id:03X} or the classic layout "
        f"{', '.join(f'0x{i:03X}' for i in classic_ids)}"
    )


def _refuse_without_samples(
    p: Path,
    got: _Sorted,
    bad_lines: list[tuple[int, str]],
    notes: dict[str, str],
    samples: str,
) -> None:
    """One line when the capture holds no CAN frame, or none with a sample ID."""
    if got.total == 0:
        why = (
            f" ({len(bad_lines)} malformed lines, first {p.name}:{bad_lines[0][0]}: "
            f"{bad_lines[0][1]})"
            if bad_lines
            else ""
        )
        raise CaptureError(f"{p}: holds no CAN frames{why}{_note(notes)}")
    if not got.fd_data and not got.classic:
        ids = ", ".join(f"0x{i:X}" for i in got.foreign_ids)
        raise CaptureError(
            f"{p}: none of its {got.total} CAN frames is a sample frame ({samples}); "
            f"{got.other} have other IDs (e.g. {ids}){_note(notes)}"
        )


@dataclass
class _Decoded:
    frames: np.ndarray
    ts: np.ndarray
    step: int
    layout: str
    reasons: list[tuple[int, str]]
    counts: dict[str, int]


def _decode_fd_samples(proto: FluxdriveProtocol, got: _Sorted) -> _Decoded:
    """The SAMPLE_FD frames through the vectorised decoder; one sent without the FD flag
    is malformed. The classic parts, if any, count as other messages."""
    payloads, lens = pack_payloads(got.fd_data, proto.fd_codec.length)
    frames, res = proto.decode_fd(payloads, lens)
    valid = res.report.valid.copy()
    not_fd = ~np.asarray(got.fd_isfd, dtype=bool)
    for i in np.flatnonzero(not_fd & valid):
        res.report.reasons[int(i)] = "sent as a classic CAN frame (FD flag clear)"
    valid &= ~not_fd
    reasons = [(int(i), res.report.reasons[int(i)]) for i in np.flatnonzero(~valid)[:100]]
    frames = frames[valid]
    return _Decoded(
        frames=frames,
        ts=np.asarray(got.fd_ts, dtype=np.float64)[valid],
        step=_infer_step(frames[:, FR_SEQ], 1),
        layout="fd" if got.fd_data else "none",
        reasons=reasons,
        counts={
            "sample": len(got.fd_data),
            "decoded": int(valid.sum()),
            "malformed": int((~valid).sum()),
            "other": got.other + len(got.classic),
        },
    )


def _reassemble_classic(
    proto: FluxdriveProtocol, got: _Sorted, classic_step: int | None
) -> _Decoded:
    """The classic layout's four parts per sample reassembled into frames."""
    ra = ClassicReassembler(protocol=proto)
    rows, tss = [], []
    for aid, data, t in got.classic:
        r = ra.feed(aid, data)
        if r is not None:
            rows.append(r)
            tss.append(t)
    frames = np.vstack(rows) if rows else np.empty((0, len(FRAME_FIELDS)))
    return _Decoded(
        frames=frames,
        ts=np.asarray(tss, dtype=np.float64),
        step=classic_step or _infer_step(frames[:, FR_SEQ], proto.classic_decimation),
        layout="classic",
        reasons=list(enumerate(ra.reasons)),
        counts={
            "sample": len(got.classic),
            "decoded": ra.completed,
            "malformed": ra.malformed,
            "incomplete": ra.incomplete,
        },
    )


def read_capture(
    path: str | os.PathLike[str],
    *,
    sample_id: int = ID_SAMPLE_FD,
    classic_ids: Sequence[int] = CLASSIC_SAMPLE_IDS,
    classic_step: int | None = None,
    protocol: FluxdriveProtocol | None = None,
) -> CaptureResult:
    """Read a .log/.asc/.blf/.trc capture and decode its sample frames.

    FD samples (``sample_id``, 64 bytes) go through the vectorised decoder; if the log
    holds no FD samples but classic-layout frames (``classic_ids``) they are
    reassembled, with the seq step taken as ``classic_step`` (default: the DBC's
    ClassicDecimation). Malformed frames are counted and skipped, never raised."""
    p = Path(path)
    _check_suffix(p)
    proto = protocol or get_protocol()
    bad_lines: list[tuple[int, str]] = []
    notes: dict[str, str] = {}
    if not p.is_file():
        raise CaptureError(f"{p}: no such capture file")
    got = _sort_messages(_messages(p, bad_lines, notes), sample_id, classic_ids)
    samples = _samples_text(sample_id, classic_ids)
    _refuse_without_samples(p, got, bad_lines, notes, samples)
    if got.fd_data or not got.classic:
        dec = _decode_fd_samples(proto, got)
    else:
        dec = _reassemble_classic(proto, got, classic_step)
    counts = {
        "total": got.total,
        "other": got.other,
        "error_frames": got.errors,
        "malformed_lines": len(bad_lines),
        **dec.counts,
    }
    # only new samples: a capture of a bus with repeats or replays on it holds each once
    sf = SeqFilter(step=dec.step, window=max(len(dec.frames), 1), resync_after=8)
    keep, _ = sf.accept(dec.frames[:, FR_SEQ].astype(np.int64), dec.ts, proto.pwm_frequency)
    dec.frames, dec.ts = dec.frames[keep], dec.ts[keep]
    st = sf.stats
    counts.update(
        gaps=st.gaps,
        lost=st.lost,
        duplicates=st.duplicates,
        out_of_order=st.out_of_order,
        jumps=st.jumps,
        resyncs=st.resyncs,
        rejected=st.rejected,
        kept=int(keep.sum()),
    )
    if not len(dec.frames):
        raise CaptureError(
            f"{p}: none of its {got.total} CAN frames is a valid sample frame ({samples}); "
            f"{counts.get('malformed', 0)} malformed"
        )
    return CaptureResult(
        frames=dec.frames,
        timestamps=dec.ts,
        counts=counts,
        layout=dec.layout,
        reasons=dec.reasons,
        bad_lines=bad_lines[:20],
        step=dec.step,
        truncated=notes.get("truncated", ""),
    )


def _infer_step(wire_seq: np.ndarray, default: int) -> int:
    """The decimation D of a capture: the most common step of its 16-bit sequence counter
    (a sample every D PWM periods carries seq k = j D)."""
    if len(wire_seq) < 3:
        return default
    d = np.mod(np.diff(wire_seq.astype(np.int64)), 1 << SEQ_BITS)
    d = d[(d > 0) & (d < 256)]
    if not len(d):
        return default
    vals, cnt = np.unique(d, return_counts=True)
    return int(vals[np.argmax(cnt)])


class CaptureError(ValueError):
    """A capture that cannot be imported; the message names the file (one line)."""


class _Lines:
    """The lines of a text capture, counting where the reader is (for file:line)."""

    def __init__(self, lines: list[str]) -> None:
        self.lines = lines
        self.i = 0  # lines handed out so far = 1-based number of the current line

    def __iter__(self) -> _Lines:
        return self

    def close(self) -> None:  # the reader closes its file when done
        pass

    @property
    def closed(self) -> bool:
        return False

    def __next__(self) -> str:
        if self.i >= len(self.lines):
            raise StopIteration
        self.i += 1
        return self.lines[self.i - 1]


def _note(notes: dict[str, str]) -> str:
    return f"; {notes['truncated']}" if notes.get("truncated") else ""


def _messages(
    p: Path, bad_lines: list[tuple[int, str]], notes: dict[str, str] | None = None
) -> Iterable[can.Message]:
    """python-can's reader for the capture; a text capture (.log/.asc/.trc) goes line by line:
    a line the reader cannot parse is skipped and noted (line number, reason) and reading
    goes on after it.  A binary capture (.blf) that python-can cannot read is one error; one
    that ends before the size its header records (a copy cut short, a logger that did not
    finish), or breaks off after some frames, gives the frames before the cut and a note
    in notes["truncated"]."""
    notes = {} if notes is None else notes
    suffix = p.suffix.lower()
    if suffix == ".blf":
        n = 0
        size = p.stat().st_size
        try:
            with can.LogReader(str(p)) as blf:
                recorded = int(getattr(blf, "file_size", 0) or 0)
                for msg in blf:
                    n += 1
                    yield msg
        except Exception as exc:  # noqa: BLE001 - BLFParseError, struct/zlib errors, ...
            why = f"{type(exc).__name__}: {str(exc).strip()[:120] or 'damaged'}"
            if n == 0:
                raise CaptureError(f"{p}: not a readable BLF capture ({why})") from None
            notes["truncated"] = f"truncated or damaged after {n} CAN frames ({why})"
            return
        if recorded == 0:
            notes["truncated"] = (
                "its header records no file size (the logger did not finish the file): "
                "it may end early"
            )
        elif size < recorded:
            notes["truncated"] = (
                f"truncated: {size} of the {recorded} bytes its header records "
                f"({n} CAN frames before the cut)"
            )
        return
    try:
        text = p.read_text(errors="replace")
    except OSError as exc:
        raise CaptureError(f"{p}: cannot read ({exc.strerror or exc})") from None
    src = _Lines(text.splitlines(keepends=True))
    kw = {"relative_timestamp": False} if suffix == ".asc" else {}  # .asc: absolute times
    # the format readers are file-based: .file is theirs, not the MessageReader interface's
    reader: Any = can.LogReader(str(p), **kw)
    reader.file.close()
    reader.file = src
    while True:
        try:
            yield from reader
            return
        except Exception as exc:  # noqa: BLE001 - the reader's parse error on one line
            if src.i >= len(src.lines):  # not a line's fault: the end of the file
                return
            bad_lines.append((src.i, f"{type(exc).__name__}: {str(exc).strip()[:80]}"))
            if hasattr(reader, "_extract_header"):  # .asc: the header was read already
                reader._extract_header = lambda: None  # type: ignore[method-assign]


def write_capture(
    path: str | os.PathLike[str],
    payloads: np.ndarray | Iterable[bytes | bytearray],
    *,
    arbitration_id: int | Sequence[int] = ID_SAMPLE_FD,
    timestamps: np.ndarray | Sequence[float] | None = None,
    t0: float = 1_700_000_000.0,
    period: float = 1e-4,
    is_fd: bool | None = None,
    bitrate_switch: bool = True,
    channel: str | int = "can0",
) -> int:
    """Write payloads as a capture file (format from the suffix) with python-can's
    writers, for tests and for shipping emulator recordings. ``arbitration_id`` is one
    ID for all frames or one per frame; timestamps default to ``t0 + k*period`` [s];
    ``is_fd`` defaults to "payload longer than 8 bytes". Returns the frame count."""
    p = Path(path)
    _check_suffix(p, WRITE_SUFFIXES)
    if isinstance(payloads, np.ndarray):
        rows = [r.tobytes() for r in np.asarray(payloads, dtype=np.uint8)]
    else:
        rows = [bytes(r) for r in payloads]
    n = len(rows)
    ids = [int(arbitration_id)] * n if isinstance(arbitration_id, int) else list(arbitration_id)
    if len(ids) != n:
        raise ValueError("one arbitration ID per payload expected")
    ts = (t0 + period * np.arange(n)) if timestamps is None else np.asarray(timestamps, float)
    ch: str | int = channel
    if p.suffix.lower() == ".blf" and isinstance(channel, str):
        ch = 1  # BLF stores numeric channels
    with open_writer(p) as writer:
        for i, data in enumerate(rows):
            fd = len(data) > 8 if is_fd is None else is_fd
            writer.on_message_received(
                can.Message(
                    timestamp=float(ts[i]),
                    arbitration_id=ids[i],
                    is_extended_id=False,
                    is_fd=fd,
                    bitrate_switch=bitrate_switch and fd,
                    data=data,
                    channel=ch,
                )
            )
    return n
