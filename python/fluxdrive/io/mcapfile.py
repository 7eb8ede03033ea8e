"""The MCAP file under the project's bag writer (fluxdrive.io.bagio.BagWriter), written in bulk.

A 10 kHz graph hands its bag writer about ten messages per PWM period.  The `mcap` library's
Writer builds a Python object and several small writes per message (about 9 us each with
rosbags on top: most of a core at 10 kHz).  Here messages wait, until a chunk is cut, as
segments: the bytes they came in (a pipe read of the recorder's stream) with numpy arrays of
where each message's data lies, its channel and its log time -- no Python object per message
(a retained object per message cost more in garbage-collector passes over this process's
heap than everything else).  The chunk's message records, sequence numbers and message
indexes are then built with numpy for the whole chunk at once: one structured array of
31-byte record heads, one join of heads and data slices, one compression.

The file is what the library would write, and every MCAP reader opens it: header; schemas
and channels (in the data section, each written when it is added, so a stream reader --
`bag recover` -- knows them before the first chunk that uses them); chunks (zstd level 1,
messages in log-time order, arrival order among equal times, a sequence number per channel
counting from 1) each followed by its message indexes; metadata records; data end; the
summary (schemas, channels, statistics, chunk indexes, metadata indexes, summary offsets)
and the footer.  zstd level 1 instead of the library's default 3: half the CPU for a file
1 % larger (measured on a demo graph's chunks: 1.9 against 3.6 ns a byte, ratio 3.12 against
3.15).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

MAGIC = b"\x89MCAP0\r\n"
OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX = 0x05, 0x06, 0x07
ZSTD_LEVEL = 1
CHUNK_BYTES = 1 << 20  # a chunk is cut once its messages reach this size (uncompressed)
# a Message record's head: opcode, record length, channel id, sequence, log time, publish time
MESSAGE_HEAD = np.dtype(
    [("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")]
)
MESSAGE_HEAD_BYTES = MESSAGE_HEAD.itemsize  # 31
_CHUNK_HEAD = struct.Struct("<BQQQQI")  # opcode, length, start, end, uncompressed size, crc
_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, length, channel id, entries' byte length


class McapFile:
    """One MCAP file, profile ros2: `add_schema`, `add_channel`, then messages one by one
    (`add`) or in bulk (`add_many`); `flush` closes the open chunk; `finish` writes the
    metadata, the summary and the footer; `abort` just closes the file (the complete
    chunks stay readable for a stream reader)."""

    def __init__(self, path: Path, *, library: str = "fluxdrive", chunk_bytes: int | None = None):
        from mcap.data_stream import RecordBuilder
        from mcap.records import Header

        self.path = Path(path)
        self.fh = self.path.open("xb")
        self.chunk_bytes = CHUNK_BYTES if chunk_bytes is None else chunk_bytes
        self.schemas: list[Any] = []
        self.channels: list[Any] = []
        self.chunk_indexes: list[Any] = []
        self.metadata_indexes: list[Any] = []
        self.channel_counts: dict[int, int] = defaultdict(int)
        self.seq = np.zeros(1, np.int64)  # by channel id: the last sequence number given
        self.t_range: tuple[int, int] | None = None  # first and last log time in the file
        self.metadata_count = 0
        # the open chunk: segments (bytes, data offsets, sizes, channel ids, log times) and the
        # messages added one by one since the last segment; no object per message is kept
        self.segments: list[tuple[bytes, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.p_ch: list[int] = []
        self.p_t: list[int] = []
        self.p_data: list[Any] = []
        self.p_bytes = 0
        rb = RecordBuilder()
        Header(profile="ros2", library=library).write(rb)
        self._write(MAGIC + rb.end())

    def _write(self, raw: bytes) -> int:
        """Append to the file; the offset it was written at."""
        at = self.fh.tell()
        self.fh.write(raw)
        return at

    def _record(self, record: Any) -> tuple[int, int]:
        """One record of the mcap library's classes into the file: (offset, length)."""
        from mcap.data_stream import RecordBuilder

        rb = RecordBuilder()
        record.write(rb)
        raw = rb.end()
        return self._write(raw), len(raw)

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        from mcap.records import Schema

        schema = Schema(id=len(self.schemas) + 1, name=name, encoding=encoding, data=data)
        self.schemas.append(schema)
        self._record(schema)
        return schema.id

    def add_channel(self, topic: str, encoding: str, schema_id: int, metadata: dict) -> int:
        from mcap.records import Channel

        channel = Channel(
            id=len(self.channels) + 1,
            topic=topic,
            message_encoding=encoding,
            schema_id=schema_id,
            metadata=dict(metadata),
        )
        self.channels.append(channel)
        self.seq = np.append(self.seq, 0)
        self._record(channel)
        return channel.id

    def add(self, channel_id: int, log_time: int, data: bytes | memoryview) -> None:
        self.p_ch.append(channel_id)
        self.p_t.append(log_time)
        self.p_data.append(data)
        self.p_bytes += len(data) + MESSAGE_HEAD_BYTES
        if self.p_bytes >= self.chunk_bytes:
            self.flush(sync=False)

    def _seal(self) -> None:
        """The messages added one by one into a segment of their own."""
        if self.p_ch:
            size = np.fromiter(map(len, self.p_data), np.int64, len(self.p_data))
            first = np.cumsum(size) - size
            ch, t = np.array(self.p_ch, np.int64), np.array(self.p_t, np.int64)
            self.segments.append((b"".join(self.p_data), first, size, ch, t))
            self.p_ch, self.p_t, self.p_data = [], [], []

    def add_many(
        self, src: bytes, first: np.ndarray, size: np.ndarray, ch: np.ndarray, t: np.ndarray
    ) -> None:
        """Messages in bulk: message i is src[first[i] : first[i] + size[i]] on channel ch[i]
        at log time t[i].  Chunks are cut where `add` one by one would cut them."""
        self._seal()
        ends = np.cumsum(size + MESSAGE_HEAD_BYTES)
        i, base = 0, 0
        while i < len(first):
            # the message that takes the open chunk to chunk_bytes closes it
            j = int(np.searchsorted(ends, base + self.chunk_bytes - self.p_bytes)) + 1
            j = min(j, len(first))
            self.segments.append((src, first[i:j], size[i:j], ch[i:j], t[i:j]))
            self.p_bytes += int(ends[j - 1]) - base
            base = int(ends[j - 1])
            i = j
            if self.p_bytes >= self.chunk_bytes:
                self.flush(sync=False)

    def flush(self, sync: bool = True) -> None:
        """Close the open chunk (if it holds messages) and push the file to the disk."""
        self._seal()
        if self.segments:
            self._write_chunk()
        self.fh.flush()
        if sync:
            os.fsync(self.fh.fileno())

    def _open_chunk(self) -> tuple[bytes, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The open chunk's segments as one: (bytes, offsets, sizes, channel ids, times)."""
        segs = self.segments
        if len(segs) == 1:
            return segs[0]
        srcs = {id(sg[0]): sg[0] for sg in segs}  # a pipe read may hold several segments
        at, n = {}, 0
        for key, src in srcs.items():
            at[key] = n
            n += len(src)
        first = np.concatenate([sg[1] + at[id(sg[0])] for sg in segs])
        size, ch, t = (np.concatenate([sg[k] for sg in segs]) for k in (2, 3, 4))
        return b"".join(srcs.values()), first, size, ch, t

    def _chunk_records(self) -> tuple[bytes, np.ndarray, np.ndarray, np.ndarray]:
        """The open chunk's message records in log-time order (arrival order among equal
        times), their channel ids, log times and offsets in the chunk."""
        src, first, size, ch, t = self._open_chunk()
        order = np.argsort(t, kind="stable")
        first, size, ch, t = first[order], size[order], ch[order], t[order]
        # sequence numbers: per channel, 1, 2, ... through the file, in log-time order
        by_ch = np.argsort(ch, kind="stable")
        per_ch = np.bincount(ch, minlength=len(self.seq))
        rank = np.empty(len(ch), np.int64)
        rank[by_ch] = np.arange(len(ch)) - np.repeat(np.cumsum(per_ch) - per_ch, per_ch)
        head = np.empty(len(ch), MESSAGE_HEAD)
        head["op"] = OP_MESSAGE
        head["len"] = size + (MESSAGE_HEAD_BYTES - 9)
        head["ch"] = ch
        head["seq"] = self.seq[ch] + rank + 1
        head["log"] = t
        head["pub"] = t
        self.seq += per_ch
        # bytes slices, not memoryviews: bytes are not tracked by the garbage collector, whose
        # full passes over this process's heap cost more than the slicing itself
        heads = head.tobytes()
        w = MESSAGE_HEAD_BYTES
        joined: list[Any] = [None] * (2 * len(ch))
        joined[0::2] = [heads[i : i + w] for i in range(0, len(ch) * w, w)]
        ends = (first + size).tolist()
        joined[1::2] = [src[a:b] for a, b in zip(first.tolist(), ends, strict=True)]
        offset = np.cumsum(size + w) - (size + w)
        return b"".join(joined), ch, t, offset

    def _write_chunk(self) -> None:
        """The open chunk into the file, then its message indexes (one per channel in it, in
        the order the channels first appear)."""
        from mcap.records import ChunkIndex

        raw, ch, t, offset = self._chunk_records()
        packed = _zstd().compress(raw)
        t0, t1 = int(t[0]), int(t[-1])
        head = _CHUNK_HEAD.pack(OP_CHUNK, 44 + len(packed), t0, t1, len(raw), zlib.crc32(raw))
        tail = struct.pack("<I4sQ", 4, b"zstd", len(packed))
        at = self._write(head + tail + packed)
        chunk_length = self.fh.tell() - at
        index_at = self.fh.tell()
        offsets: dict[int, int] = {}
        indexes: list[bytes] = []
        ids, first = np.unique(ch, return_index=True)
        for c in ids[np.argsort(first)].tolist():
            mine = ch == c
            pairs = np.empty((int(mine.sum()), 2), "<u8")
            pairs[:, 0] = t[mine]
            pairs[:, 1] = offset[mine]
            offsets[c] = index_at + sum(len(x) for x in indexes)
            indexes.append(_INDEX_HEAD.pack(OP_MESSAGE_INDEX, 6 + pairs.nbytes, c, pairs.nbytes))
            indexes.append(pairs.tobytes())
            self.channel_counts[c] += len(pairs)
        self._write(b"".join(indexes))
        self.chunk_indexes.append(
            ChunkIndex(
                message_start_time=t0,
                message_end_time=t1,
                chunk_start_offset=at,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=self.fh.tell() - index_at,
                compression="zstd",
                compressed_size=len(packed),
                uncompressed_size=len(raw),
            )
        )
        self.t_range = (
            (t0, t1)
            if self.t_range is None
            else (min(self.t_range[0], t0), max(self.t_range[1], t1))
        )
        self.segments = []
        self.p_bytes = 0

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (after the open chunk), indexed in the summary."""
        from mcap.records import Metadata, MetadataIndex

        self.flush(sync=False)
        at, length = self._record(Metadata(name=name, metadata=data))
        self.metadata_indexes.append(MetadataIndex(offset=at, length=length, name=name))
        self.metadata_count += 1

    def finish(self) -> None:
        """The open chunk, data end, the summary and the footer; closes the file."""
        from mcap.records import DataEnd

        self.flush(sync=False)
        self._record(DataEnd(data_section_crc=0))
        summary_at = self.fh.tell()
        summary, offsets_at = self._summary(summary_at)
        self._write(summary)
        footer = struct.pack("<BQQQ", 0x02, 20, summary_at, summary_at + offsets_at)
        crc = zlib.crc32(footer, zlib.crc32(summary))
        self._write(footer + struct.pack("<I", crc) + MAGIC)
        self.fh.close()

    def _summary(self, summary_at: int) -> tuple[bytes, int]:
        """The summary section's bytes and where its summary offsets start (relative)."""
        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import Statistics, SummaryOffset

        t0, t1 = self.t_range or (0, 0)
        stats = Statistics(
            message_count=sum(self.channel_counts.values()),
            schema_count=len(self.schemas),
            channel_count=len(self.channels),
            attachment_count=0,
            metadata_count=self.metadata_count,
            chunk_count=len(self.chunk_indexes),
            message_start_time=t0,
            message_end_time=t1,
            channel_message_counts=dict(self.channel_counts),
        )
        groups = [
            (Opcode.SCHEMA, self.schemas),
            (Opcode.CHANNEL, self.channels),
            (Opcode.STATISTICS, [stats]),
            (Opcode.CHUNK_INDEX, self.chunk_indexes),
            (Opcode.METADATA_INDEX, self.metadata_indexes),
        ]
        rb = RecordBuilder()
        offsets = []
        for opcode, records in groups:
            if not records:  # no offset pointing at an empty group
                continue
            start = rb.count
            for r in records:
                r.write(rb)
            offsets.append(SummaryOffset(opcode, summary_at + start, rb.count - start))
        offsets_at = rb.count
        for o in offsets:
            o.write(rb)
        return rb.end(), offsets_at

    def abort(self) -> None:
        """Close without the summary (the complete chunks stay readable for `bag recover`)."""
        self.fh.close()


_ZSTD = None


def _zstd():
    global _ZSTD
    if _ZSTD is None:
        import zstandard

        _ZSTD = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    return _ZSTD
