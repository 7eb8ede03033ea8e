"""A valid bag from one that was not finalised (`./fluxdrive bag recover BAG_DIR [--out DIR]`,
fluxdrive.cli.bag).

A recorder killed together with its bag writer (SIGKILL of its process group, a power cut)
or stopped by a failing write (disk full) leaves BAG_DIR/<name>.mcap without its summary
and footer, and no metadata.yaml.  The MCAP data section is still a sequence of complete
records: the schemas and channels, then chunks of messages (closed every
`flush_interval_s` or 1 MiB by the recorder's writer, see fluxdrive.io.bagwriter).
This reads it front to back with the mcap library's StreamReader (no summary needed; a
chunk's messages are used only once the whole chunk was read), stops at the first
truncated or corrupt record, and writes every message read so far into a new rosbag2 bag
(version 9, MCAP, message definitions embedded, the run's custom_data from the
recording.json the writer left behind) with the same writer as the recorder (rosbags,
the project's typestore from fluxdrive.io.bagio).  It prints the messages recovered
per topic, the time span and, for /drive/frame, the sequence range and any gap.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fluxdrive.core.machine import ConfigError
from fluxdrive.io.bagio import META_KEY, BagWriter, typestore
from fluxdrive.io.bagwriter import RECORDING_FILE
from fluxdrive.io.messages import message_seq


@dataclass
class Recovery:
    source: Path
    out: Path
    counts: dict[str, int] = field(default_factory=dict)
    t_first_ns: int | None = None
    t_last_ns: int = 0
    chunks: int = 0
    bytes_read: int = 0
    bytes_total: int = 0
    stop_reason: str = ""
    frame_seqs: tuple[int, int, int] | None = None  # first, last, gaps (count of missing)

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def mcap_file(bag: Path) -> Path:
    if bag.is_file() and bag.suffix == ".mcap":
        return bag
    if not bag.is_dir():
        raise ConfigError(f"bag recover: {bag} is neither a bag directory nor an .mcap file")
    files = sorted(bag.glob("*.mcap"))
    if len(files) != 1:
        raise ConfigError(
            f"bag recover: expected one .mcap file in {bag}, found "
            f"{[f.name for f in files] or 'none'}"
        )
    return files[0]


def is_finalised(mcap: Path) -> bool:
    """The file ends with the MCAP footer magic and its bag has metadata.yaml."""
    magic = b"\x89MCAP0\r\n"
    size = mcap.stat().st_size
    if size < 2 * len(magic) or not (mcap.parent / "metadata.yaml").exists():
        return False
    with open(mcap, "rb") as fh:
        fh.seek(size - len(magic))
        return fh.read() == magic


def recover(bag: Path, out: Path | None = None) -> Recovery:
    """Read what is readable of bag's MCAP file and write it to `out` (default
    <bag>-recovered) as a new, finalised bag."""

    mcap = mcap_file(Path(bag))
    bag_dir = mcap.parent
    out = Path(out) if out is not None else bag_dir.with_name(bag_dir.name + "-recovered")
    if out.exists():
        raise ConfigError(f"bag recover: {out} exists already; give --out a new directory")
    rec = Recovery(source=mcap, out=out, bytes_total=mcap.stat().st_size)
    custom = _recorded_custom_data(bag_dir / RECORDING_FILE, rec)
    try:
        settings = json.loads(custom[META_KEY]) if META_KEY in custom else {}
    except ValueError:
        settings = {}
    # the recorded log times are already on the epoch: no second offset
    writer = BagWriter(out, settings, epoch_offset_ns=0)
    copy = _ChunkCopy(writer, rec)
    try:
        copy.run(mcap)
    except ConfigError:  # not a bag this can rebuild: no half bag left behind
        import contextlib
        import shutil

        with contextlib.suppress(Exception):
            writer.abort()
        shutil.rmtree(out, ignore_errors=True)
        raise
    except BaseException:
        writer.close()
        raise
    writer.close()
    if copy.first_seq is not None:
        rec.frame_seqs = (copy.first_seq, copy.last_seq, copy.gaps)
    if not copy.conns:
        import shutil

        shutil.rmtree(out, ignore_errors=True)
        raise ConfigError(f"bag recover: nothing readable in {mcap} ({rec.stop_reason})")
    return rec


def _recorded_custom_data(side: Path, rec: Recovery) -> dict[str, str]:
    """The run's custom_data the bag writer left in RECORDING_FILE ({} without it)."""
    if not side.exists():
        return {}
    try:
        return dict(json.loads(side.read_text()).get("custom_data") or {})
    except (OSError, ValueError) as exc:
        rec.stop_reason = f"{side} unreadable ({exc}); custom_data not recovered. "
        return {}


def _stop_reason(exc: Exception, rec: Recovery, at_end_of_file: bool) -> str:
    """Why the readable part ends: the data simply stops (no summary), the file ends inside a
    record (a short read: the mcap library raises EndOfFile or, inside a record's length
    field, struct.error), or damage before the end."""
    if type(exc).__name__ == "EndOfFile" and rec.bytes_read == rec.bytes_total:
        what = "the data ends there, without the summary (not finalised)"
    elif at_end_of_file:
        what = "the file ends inside a record (the writer stopped there)"
    else:
        what = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return f"stopped at byte {rec.bytes_read}: {what}"


class _ChunkCopy:
    """The records of an MCAP file, front to back, into a bag writer: schemas and channels
    become connections, messages of complete chunks are written; /drive/frame's seq range and
    gaps are counted on the way."""

    def __init__(self, writer, rec: Recovery):
        self.writer = writer
        self.rec = rec
        self.store = typestore()
        self.schemas: dict[int, Any] = {}
        self.conns: dict[int, int] = {}  # MCAP channel id -> writer connection
        self.topic_of: dict[int, str] = {}
        self.first_seq: int | None = None
        self.last_seq = 0  # set with first_seq
        self.gaps = 0

    def run(self, mcap: Path) -> None:
        from mcap.records import Channel, Chunk, Message, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk

        rec = self.rec
        with open(mcap, "rb") as fh:
            records = StreamReader(fh, emit_chunks=True, validate_crcs=True).records
            while True:
                try:
                    r = next(records)
                    # a chunk counts only once it is complete and decodes (CRC if present)
                    inner = breakup_chunk(r, validate_crc=True) if isinstance(r, Chunk) else [r]
                except StopIteration:
                    rec.stop_reason += "the file is complete (it has its footer)"
                    break
                except Exception as exc:  # noqa: BLE001 - any damage ends the readable part
                    rec.stop_reason += _stop_reason(exc, rec, fh.tell() >= rec.bytes_total)
                    break
                rec.bytes_read = fh.tell()
                rec.chunks += isinstance(r, Chunk)
                for x in inner:
                    if isinstance(x, Message):
                        self.message(x)
                    elif isinstance(x, Schema):
                        self.schemas[x.id] = x
                    elif isinstance(x, Channel) and x.id not in self.conns:
                        self.channel(x)

    def message(self, x) -> None:
        conn = self.conns.get(x.channel_id)
        if conn is None:
            return
        rec = self.rec
        self.writer.write(conn, x.log_time, x.data)
        topic = self.topic_of[x.channel_id]
        rec.counts[topic] += 1
        if rec.t_first_ns is None or x.log_time < rec.t_first_ns:
            rec.t_first_ns = x.log_time
        rec.t_last_ns = max(rec.t_last_ns, x.log_time)
        if topic == "/drive/frame":
            sq = message_seq(x.data)
            if self.first_seq is None:
                self.first_seq = sq
            elif sq != self.last_seq + 1:
                self.gaps += abs(sq - self.last_seq - 1)
            self.last_seq = sq

    def channel(self, x) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        sch = self.schemas.get(x.schema_id)
        if sch is None:
            return
        if x.message_encoding != "cdr" or sch.encoding != "ros2msg":
            # a foreign MCAP (JSON, protobuf, ...): not a rosbag2 bag, nothing to rebuild
            raise ConfigError(
                f"bag recover: {x.topic} is encoded {x.message_encoding!r} with a "
                f"{sch.encoding!r} schema; only rosbag2 bags (cdr, ros2msg) are recovered"
            )
        ts = self.store
        if sch.name not in self.store.fielddefs:  # not ours: its embedded text
            ts = get_typestore(Stores.EMPTY)
            ts.register(get_types_from_msg(sch.data.decode(), sch.name))
        self.conns[x.id] = self.writer.add_connection(x.topic, sch.name, ts)
        self.topic_of[x.id] = x.topic
        self.rec.counts[x.topic] = 0


def report(rec: Recovery) -> str:
    lines = [
        f"bag recover: {rec.source}: read {rec.bytes_read} of {rec.bytes_total} bytes, "
        f"{rec.chunks} complete chunks; {rec.stop_reason}",
        f"recovered {rec.messages} messages into {rec.out} (rosbag2 v9, MCAP):",
    ]
    w = max((len(t) for t in rec.counts), default=10)
    for t, c in rec.counts.items():
        lines.append(f"  {t:{w}s} {c:9d}")
    if rec.t_first_ns is not None:
        t0, t1 = rec.t_first_ns * 1e-9, rec.t_last_ns * 1e-9
        lines.append(f"time span {t0:.4f} .. {t1:.4f} s ({t1 - t0:.4f} s)")
    if rec.frame_seqs is not None:
        a, b, gaps = rec.frame_seqs
        lines.append(
            f"/drive/frame seq {a}..{b}, "
            + ("no gaps" if gaps == 0 else f"{gaps} frames missing inside")
        )
    return "\n".join(lines)
