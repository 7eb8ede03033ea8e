"""The recorder's bag-writing helper process (`python -m fluxdrive.cli.bagwriter`, this
module's write_stream): serialised messages in on stdin, a rosbag2 bag
(fluxdrive.io.bagio.BagWriter: MCAP storage, version 9, message definitions embedded) out.

Why a process: writing a bag costs CPU per message; at 10 kHz with ten topics, inside the
recorder's process it would fight the executor for the GIL.  Here it runs on the other core.
The recorder only appends bytes to a buffer; a feeder thread ships the buffer down the pipe
every 20 ms.  This side reads the pipe as it comes and hands the messages of each read to the
bag writer in one call (BagWriter.write_many: the MCAP chunks are built with numpy a chunk
at a time, fluxdrive.io.mcapfile), so the Python left per message is the parse of its
15-byte head.

It ignores SIGINT/SIGTERM (the recorder owns the run's end) and finalises the bag when its
input ends: on the recorder's end marker, or on EOF because the recorder died -- so even a
SIGKILLed recorder leaves a finalised bag with everything it had handed over.

Crash safety: the MCAP data section is a sequence of chunks; a chunk goes to the file when
it reaches 1 MiB or on the recorder's flush marker (every `flush_interval_s`,
default 0.5 s), whichever comes first, and the file is flushed and fsync'ed then.  If this
process is killed too (SIGKILL of the recorder's process group, a power cut after the
fsync), the file lacks only its summary and the open chunk: `./fluxdrive bag recover DIR`
(fluxdrive.io.bagrecover) rebuilds a valid bag from the complete chunks.  While the
bag is open, RECORDING_FILE in the bag directory keeps what metadata.yaml would get at the
end (custom_data), for the recovery; it is removed once the bag is finalised.
What such a kill loses is bounded in bytes by the path a message takes: the recorder's
backlog (its `max_backlog_mb`; its callbacks wait beyond it) and the batch its feeder has
taken off it and waits to write (at most as much again), the pipe (PIPE_BYTES of
fluxdrive.cli.bagwriter), this side's read not yet in the bag (READ_BYTES) and the open chunk
(fluxdrive.io.mcapfile.CHUNK_BYTES).

A failing write (disk full, file too large, I/O error) stops the recording: "error
<reason>" on stdout (the recorder logs it), the file is closed without its summary (its
complete chunks stay readable for `bag recover`) and the process exits with code 3.

Protocol on stdin (little endian):
  b"H" u32 n, JSON {"path": str, "custom_data": {key: str},      first record; opens the bag
                    "epoch_offset_ns": int}                     (bag time = stamp + offset)
  b"C" u32 n, JSON {"id": int, "topic": str, "type": str}       a connection (before use)
  b"M" u16 id, i64 t_ns, u32 n, n bytes of CDR                   a message
  b"B" u32 n, then n bytes: u16 k, k x (u16 id, u32 count,      a block (below)
       u32 size), then topic after topic: (size 0: its count
       sizes, u32 each) its messages back to back
  b"F"                                                          flush: close the open chunk
  b"E"                                                          end: finalise and exit
A block carries several topics' sample messages (flux_drive_msgs: header, then u64 seq), each
topic's in publish order, all of one size or (size 0) of the sizes listed; their bag time is
the header stamp.  The recorder hands them over as they came (one join per topic); this side
lays them out in the bag STEP_SEQS samples at a time (`block_order`): every topic's messages
of seqs up to the next multiple, then the next STEP_SEQS, so a bag cut anywhere holds its
topics in step as message-by-message recording would.  A topic of several layouts (sizes,
frame_id lengths) goes first, as it came; seqs that go backwards: topic after topic.  A block
cut by EOF is dropped whole (its topics stay in step).
On stdout: "ready" once the bag is open, "closed <messages>" once finalised, "error <text>"
when writing failed; errors on stderr with a non-zero exit.
"""

from __future__ import annotations

import json
import struct
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from fluxdrive.io.messages import seq_offset

if TYPE_CHECKING:
    from fluxdrive.io.bagio import BagWriter

MSG_HDR = struct.Struct("<cHqI")  # b"M", id, t, n
_MSG_HEAD = MSG_HDR.size
_U32_AT = struct.Struct("<I")  # a message's data length, 11 bytes into its record
_HEAD = np.dtype([("id", "<u2"), ("t", "<i8"), ("n", "<u4")])  # a message record's head
_HEAD_BYTES = np.arange(1, _MSG_HEAD)  # after the b"M"
_M = ord("M")
U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")
BLOCK_PART = struct.Struct("<HII")  # a block's topic: recorder id, messages, size (0: listed)
_PART = np.dtype([("id", "<u2"), ("n", "<u4"), ("size", "<u4")])
STEP_SEQS = 4  # a block's topics are laid out in the bag this many samples at a time
READ_BYTES = 1 << 20  # the most one read of the input takes (then handed to the bag at once)
RECORDING_FILE = "recording.json"  # in the bag directory while the bag is being written
EXIT_WRITE_FAILED = 3


def pack_json(kind: bytes, obj: dict) -> bytes:
    raw = json.dumps(obj).encode()
    return kind + U32.pack(len(raw)) + raw


def check_bag_target(bag_dir: Path, min_free_mb: float = 0.0, must_not_exist: bool = True) -> float:
    """Can a bag be written at bag_dir?  Creates its parent directories, checks that a file
    can be written there and that at least min_free_mb are free.  Returns the free space
    [MB]; raises ValueError with a one-line reason (before anything starts recording)."""
    import errno
    import shutil
    import tempfile

    bag_dir = Path(bag_dir)
    if must_not_exist and bag_dir.exists():
        raise ValueError(f"bag directory {bag_dir} exists already; choose a new one")
    parent = bag_dir.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        if not parent.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "not a directory", str(parent))
        with tempfile.TemporaryFile(dir=parent, prefix=".fluxdrive-write-test-") as fh:
            fh.write(b"x")
            fh.flush()
    except OSError as exc:
        raise ValueError(
            f"cannot record to {bag_dir}: {parent} is not a writable "
            f"directory ({exc.strerror or exc})"
        ) from exc
    free_mb = shutil.disk_usage(parent).free / 1e6
    if free_mb < min_free_mb:
        raise ValueError(
            f"cannot record to {bag_dir}: {free_mb:.0f} MB free on its file "
            f"system, the recorder's min_free_mb is {min_free_mb:g} MB"
        )
    return free_mb


def _say(text: str) -> None:
    try:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    except (BrokenPipeError, ValueError):  # the recorder is gone
        pass


def flush_chunk(writer, sync: bool = True) -> None:
    """Close the open MCAP chunk (if it holds messages) and push the file to the disk, so a
    crash from here on loses nothing written so far."""
    writer.flush(sync)


class _BagStream:
    """One bag written from the record stream: the writer, its connections by the recorder's
    id, the messages written so far."""

    def __init__(self, inp: BinaryIO):
        # a pipe: what is there (the recorder's feeder writes every 20 ms), not a full block
        self.read: Callable[[int], bytes] = getattr(inp, "read1", inp.read)
        self.writer: BagWriter | None = None
        self.side: Path | None = None  # RECORDING_FILE while the bag is open
        self.conn_of = np.full(1, -1, np.int64)  # the recorder's id -> the writer's connection
        self.n_msgs = 0

    def copy_records(self) -> None:
        """Until the end marker, EOF or a corrupt record: every record to the bag.  The input
        is read in blocks as they come; the messages of a block go to the bag writer in one
        call (fluxdrive.io.bagio.BagWriter.write_many), a record cut by the end of a block
        waits for the next one, one cut by EOF is dropped."""
        buf = b""
        while True:
            block = self.read(READ_BYTES)
            if not block:
                return
            buf = buf + block if buf else block
            pos = 0
            while pos < len(buf):
                pos = self.messages(buf, pos)
                nxt = self.control(buf, pos) if pos < len(buf) else pos
                if nxt is None:  # a record continues in the next block
                    break
                if nxt < 0:  # the end marker or corrupt input
                    return
                pos = nxt
            buf = buf[pos:]

    def messages(self, buf: bytes, pos: int) -> int:
        """The complete message records from `pos` on (up to the first other record or the
        end of `buf`) into the bag; where they end.  Python finds where each record starts;
        numpy reads their heads."""
        end = len(buf)
        size_at = _U32_AT.unpack_from
        starts: list[int] = []
        add = starts.append
        while pos + _MSG_HEAD <= end and buf[pos] == _M:
            pos_next = pos + _MSG_HEAD + size_at(buf, pos + 11)[0]
            if pos_next > end:
                break
            add(pos)
            pos = pos_next
        if starts:
            if self.writer is None:
                raise RuntimeError("bag writer: a message before the bag's header")
            at = np.array(starts, np.int64)
            raw = np.frombuffer(buf, np.uint8)
            head = raw[at[:, None] + _HEAD_BYTES].view(_HEAD)[:, 0]
            conns = self.conn_of[head["id"]]
            if conns.min() < 0:
                raise RuntimeError("bag writer: a message before its connection")
            self.writer.write_many(conns, head["t"], buf, at + _MSG_HEAD, head["n"])
            self.n_msgs += len(starts)
        return pos

    def control(self, buf: bytes, pos: int) -> int | None:
        """The record at `pos` that is not a message: where the next one starts; None when it
        is not complete in `buf`, -1 at the end marker or corrupt input."""
        kind = buf[pos : pos + 1]
        if kind == b"F":
            flush_chunk(self.writer)
            return pos + 1
        if kind == b"E":
            return -1
        if kind == b"M":  # messages() stopped here: the record is not complete yet
            return None
        if kind not in (b"C", b"H", b"B"):
            print(f"bagwriter: corrupt input (record type {kind!r})", file=sys.stderr)
            return -1
        if pos + 5 > len(buf):
            return None
        (n,) = U32.unpack_from(buf, pos + 1)
        if pos + 5 + n > len(buf):
            return None
        if kind == b"B":
            self.block(buf, pos + 5, n)
            return pos + 5 + n
        obj = json.loads(buf[pos + 5 : pos + 5 + n])
        if kind == b"C":
            self.add_connection(obj)
        else:
            self.open_bag(obj)
            _say("ready")
        return pos + 5 + n

    def block(self, buf: bytes, pos: int, n: int) -> None:
        """A block record's messages (at `pos`, `n` bytes) into the bag, laid out in step."""
        if self.writer is None:
            raise RuntimeError("bag writer: a block before the bag's header")
        ids, first, size = block_order(buf, pos, n)
        if not len(ids):
            return
        conns = self.conn_of[ids]
        if conns.min() < 0:
            raise RuntimeError("bag writer: a block before its connection")
        t = _gather(buf, first + 4, np.dtype("<i4")).astype(np.int64) * 1_000_000_000
        t += _gather(buf, first + 8, np.dtype("<u4"))
        self.writer.write_many(conns, t, buf, first, size)
        self.n_msgs += len(ids)

    def add_connection(self, c: dict) -> None:
        if self.writer is None:
            raise RuntimeError("bag writer: a connection before the bag's header")
        rid = int(c["id"])
        if rid >= len(self.conn_of):
            self.conn_of = np.concatenate([self.conn_of, np.full(rid + 1 - len(self.conn_of), -1)])
        self.conn_of[rid] = self.writer.add_connection(c["topic"], c["type"])

    def open_bag(self, h: dict) -> None:
        """The header record: open the bag and leave RECORDING_FILE for a recovery."""
        from fluxdrive.io.bagio import META_KEY, BagWriter

        path = Path(h["path"])
        cd = h.get("custom_data") or {}
        settings = json.loads(cd[META_KEY]) if META_KEY in cd else {}
        self.writer = BagWriter(path, settings, epoch_offset_ns=h.get("epoch_offset_ns"))
        self.side = path / RECORDING_FILE
        self.side.write_text(
            json.dumps(
                {
                    "note": "this bag is being written; without metadata.yaml it was not "
                    "finalised: ./fluxdrive bag recover " + str(path),
                    "custom_data": {META_KEY: json.dumps(self.writer.settings)},
                }
            )
        )

    def write_failure(self, exc: OSError) -> str:
        writer = self.writer
        where = (
            getattr(getattr(writer, "storage", None), "path", None)
            or exc.filename
            or (writer.path if writer is not None else "the bag")
        )
        return f"cannot write {where}: {exc.strerror or exc} (after {self.n_msgs} messages)"

    def finish(self, failed: str) -> str:
        """Finalise the bag (or, after a failed write, close it without its summary) and say
        so on stdout; the reason it failed, "" when it did not."""
        writer = self.writer
        if writer is not None and not failed:
            try:
                writer.close()
                if self.side is not None:
                    self.side.unlink(missing_ok=True)
                _say(f"closed {self.n_msgs}")
            except OSError as exc:
                failed = f"cannot finalise {writer.path}: {exc.strerror or exc}"
        if failed:
            if writer is not None:
                try:  # no summary: the complete chunks stay readable for `bag recover`
                    writer.abort()
                except OSError:
                    pass
                failed += (
                    f"; the complete chunks can be recovered with "
                    f"./fluxdrive bag recover {writer.path}"
                )
            _say(f"error {failed}")  # the recorder logs it
        return failed


def _gather(buf: bytes, at: np.ndarray, dt: np.dtype) -> np.ndarray:
    """The values of type `dt` at byte offsets `at` of `buf`."""
    raw = np.frombuffer(buf, np.uint8)
    return raw[at[:, None] + np.arange(dt.itemsize)].view(dt)[:, 0]


def _block_parts(buf: bytes, pos: int, n: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """A block record's topics: (recorder id, where each message starts, its size)."""
    (k,) = _U16.unpack_from(buf, pos)
    table = np.frombuffer(buf, _PART, k, pos + 2)
    at = pos + 2 + k * _PART.itemsize
    parts = []
    for cid, count, size in table.tolist():
        if size:
            sizes = np.full(count, size, np.int64)
        else:  # the sizes, then the messages
            sizes = np.frombuffer(buf, "<u4", count, at).astype(np.int64)
            at += 4 * count
        parts.append((cid, at + np.cumsum(sizes) - sizes, sizes))
        at += int(sizes.sum())
    if at != pos + n:
        raise RuntimeError("bag writer: a block's sizes do not add up to its length")
    return parts


def block_order(buf: bytes, pos: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A block record's messages in bag order: (recorder ids, starts, sizes).  Topics of one
    layout are laid out STEP_SEQS seqs at a time (each topic's messages of seqs below the
    next multiple of STEP_SEQS, topic after topic, then the next STEP_SEQS); a topic of
    several layouts goes first, as it came; seqs that go backwards (or a block spanning more
    than a million seqs): topic after topic."""
    first_parts, step_parts, seqs = [], [], []
    for cid, first, sizes in _block_parts(buf, pos, n):
        if not len(first):
            continue
        flen = _gather(buf, first + 12, np.dtype("<u4"))  # header.frame_id's length
        if (sizes != sizes[0]).any() or (flen != flen[0]).any():
            first_parts.append((cid, first, sizes))
            continue
        off = seq_offset(buf[first[0] : first[0] + 16])
        seqs.append(_gather(buf, first + off, np.dtype("<u8")).astype(np.int64))
        step_parts.append((cid, first, sizes))
    parts = first_parts + step_parts
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    ids = np.concatenate([np.full(len(f), c, np.int64) for c, f, _ in parts])
    first = np.concatenate([f for _, f, _ in parts])
    sizes = np.concatenate([s for _, _, s in parts])
    order = _step_order(seqs)
    if order is not None:
        order = np.concatenate([np.arange(len(ids) - len(order)), order + len(ids) - len(order)])
        ids, first, sizes = ids[order], first[order], sizes[order]
    return ids, first, sizes


def _step_order(seqs: list[np.ndarray]) -> np.ndarray | None:
    """The order that lays topics with these seqs out STEP_SEQS at a time (None: as they
    are -- one topic, seqs going backwards, or more than a million seqs apart)."""
    if len(seqs) < 2:
        return None
    lo = min(int(q[0]) for q in seqs)
    hi = max(int(q[-1]) for q in seqs)
    if hi - lo > 1_000_000 or any((q[1:] < q[:-1]).any() for q in seqs):
        return None
    step = np.concatenate(seqs) // STEP_SEQS - lo // STEP_SEQS
    topic = np.repeat(np.arange(len(seqs)), [len(q) for q in seqs])
    return np.argsort(step * len(seqs) + topic, kind="stable")


def write_stream(inp: BinaryIO) -> int:
    """Write the bag the records on `inp` describe (the protocol above); the exit code."""
    stream = _BagStream(inp)
    failed = ""
    try:
        stream.copy_records()
    except OSError as exc:  # disk full, file too large, I/O error: stop recording
        failed = stream.write_failure(exc)
    finally:
        failed = stream.finish(failed)
    return EXIT_WRITE_FAILED if failed else 0
