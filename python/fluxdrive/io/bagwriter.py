"""The recorder's bag-writing helper process (`python -m fluxdrive.cli.bagwriter`, this
module's write_stream): serialised messages in on stdin, a rosbag2 bag
(fluxdrive.io.bagio.BagWriter: MCAP storage, version 9, message definitions embedded) out.

Why a process: writing with rosbags costs about 5 us of Python per message; at 10 kHz with
ten topics that is half a core, and inside the recorder's process it would fight the
executor for the GIL.  Here it runs on the other core.  The recorder only appends bytes to
a buffer; a feeder thread ships the buffer down the pipe in batches.

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

A failing write (disk full, file too large, I/O error) stops the recording: "error
<reason>" on stdout (the recorder logs it), the file is closed without its summary (its
complete chunks stay readable for `bag recover`) and the process exits with code 3.

Protocol on stdin (little endian):
  b"H" u32 n, JSON {"path": str, "custom_data": {key: str},      first record; opens the bag
                    "epoch_offset_ns": int}                     (bag time = stamp + offset)
  b"C" u32 n, JSON {"id": int, "topic": str, "type": str}       a connection (before use)
  b"M" u16 id, i64 t_ns, u32 n, n bytes of CDR                   a message
  b"F"                                                          flush: close the open chunk
  b"E"                                                          end: finalise and exit
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

if TYPE_CHECKING:
    from fluxdrive.io.bagio import BagWriter

MSG_HDR = struct.Struct("<cHqI")  # b"M", id, t, n
U32 = struct.Struct("<I")
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

    def __init__(self, read: Callable[[int], bytes]):
        self.read = read
        self.writer: BagWriter | None = None
        self.side: Path | None = None  # RECORDING_FILE while the bag is open
        self.conns: dict[int, int] = {}
        self.n_msgs = 0

    def read_json(self) -> dict:
        (n,) = U32.unpack(self.read(4))
        return json.loads(self.read(n))

    def copy_records(self) -> None:
        """Until the end marker, EOF or a corrupt record: every record to the bag."""
        read = self.read
        while True:
            kind = read(1)
            if not kind or kind == b"E":
                break
            if kind == b"M":  # the per-message path stays inline: ten topics at 10 kHz
                hdr = read(14)
                if len(hdr) < 14:
                    break
                cid, t, n = struct.unpack("<HqI", hdr)
                data = read(n)
                if len(data) < n:
                    break
                if self.writer is None:
                    raise RuntimeError("bag writer: a message before the bag's header")
                self.writer.write(self.conns[cid], t, data)
                self.n_msgs += 1
            elif kind == b"F":
                flush_chunk(self.writer)
            elif kind == b"C":
                self.add_connection(self.read_json())
            elif kind == b"H":
                self.open_bag(self.read_json())
                _say("ready")
            else:
                print(f"bagwriter: corrupt input (record type {kind!r})", file=sys.stderr)
                break

    def add_connection(self, c: dict) -> None:
        if self.writer is None:
            raise RuntimeError("bag writer: a connection before the bag's header")
        self.conns[c["id"]] = self.writer.add_connection(c["topic"], c["type"])

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


def write_stream(inp: BinaryIO) -> int:
    """Write the bag the records on `inp` describe (the protocol above); the exit code."""
    stream = _BagStream(inp.read)
    failed = ""
    try:
        stream.copy_records()
    except OSError as exc:  # disk full, file too large, I/O error: stop recording
        failed = stream.write_failure(exc)
    finally:
        failed = stream.finish(failed)
    return EXIT_WRITE_FAILED if failed else 0
