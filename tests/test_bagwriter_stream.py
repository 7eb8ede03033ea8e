"""The recorder's bag writer (fluxdrive.io.bagwriter, MCAP built in bulk by
fluxdrive.io.mcapfile): what goes down the pipe comes back out of the bag message for message
-- same bytes, same log times -- in every reader (mcap's own, rosbags, the project's), however
the pipe cuts the stream; and the bulk path writes the very file that writing the same
messages one by one does."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
from fluxdrive.io import mcapfile
from fluxdrive.io.bagio import BagWriter, read_raw
from fluxdrive.io.bagwriter import MSG_HDR, pack_json, write_stream

OFFSET_NS = 1_700_000_000_000_000_000
TOPICS = [
    (1, "/drive/frame", "flux_drive_msgs/msg/PhaseFrame"),
    (2, "/clock", "rosgraph_msgs/msg/Clock"),
    (5, "/obs/fm/estimate", "flux_drive_msgs/msg/RotorEstimate"),  # ids need not be dense
]


def sent_messages(n: int) -> list[tuple[int, int, bytes]]:
    """(recorder id, sample time [ns], payload): per period a frame and a clock, the
    estimates in blocks of 7 periods that arrive late (times out of order across topics),
    payload sizes that differ per message (seeded)."""
    rng = np.random.default_rng(7)
    out, block = [], []
    for k in range(n):
        t = k * 100_000
        out.append((1, t, rng.bytes(int(rng.integers(8, 300)))))
        out.append((2, t, struct.pack("<4siI", b"\x00\x01\x00\x00", *divmod(t, 10**9))))
        block.append((5, t, rng.bytes(64)))
        if len(block) == 7:
            out += block
            block = []
    return out + block


def stream(bag: Path, msgs: list[tuple[int, int, bytes]], flush_every: int) -> bytes:
    """The records the recorder would pipe: header, connections, messages, flush markers,
    end marker."""
    head = {"path": str(bag), "custom_data": {}, "epoch_offset_ns": OFFSET_NS}
    parts = [pack_json(b"H", head)]
    parts += [pack_json(b"C", {"id": i, "topic": t, "type": ty}) for i, t, ty in TOPICS]
    for j, (cid, t, data) in enumerate(msgs):
        parts.append(MSG_HDR.pack(b"M", cid, t, len(data)) + data)
        if j % flush_every == flush_every - 1:
            parts.append(b"F")
    return b"".join(parts) + b"E"


class Pipe(io.BytesIO):
    """A pipe's reads: whatever arrived, here blocks of seeded random sizes, so records are
    cut at every kind of place (in a header, in the data, between records)."""

    def __init__(self, raw: bytes):
        super().__init__(raw)
        self.rng = np.random.default_rng(3)

    def read1(self, n: int | None = -1) -> bytes:
        return super().read1(int(self.rng.integers(1, 900)))


def mcap_messages(bag: Path) -> tuple[list[tuple[str, int, int, int, bytes]], object]:
    """(topic, log time, publish time, sequence, data) in file order, and the summary."""
    from mcap.reader import make_reader

    (f,) = bag.glob("*.mcap")
    with f.open("rb") as fh:
        reader = make_reader(fh)
        msgs = [
            (c.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data))
            for _, c, m in reader.iter_messages(log_time_order=False)
        ]
        return msgs, reader.get_summary()


def chunk_times_sorted(bag: Path) -> bool:
    """Log times in order inside every chunk."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    (f,) = bag.glob("*.mcap")
    with f.open("rb") as fh:
        for rec in StreamReader(fh, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                t = [m.log_time for m in breakup_chunk(rec) if isinstance(m, Message)]
                if t != sorted(t):
                    return False
    return True


@pytest.fixture(autouse=True)
def small_chunks(monkeypatch):
    monkeypatch.setattr(mcapfile, "CHUNK_BYTES", 8192)  # several chunks from a short stream


def test_every_message_comes_back_with_its_bytes_and_times(tmp_path, capsys):
    sent = sent_messages(400)
    bag = tmp_path / "bag"
    assert write_stream(Pipe(stream(bag, sent, flush_every=150))) == 0
    assert capsys.readouterr().out.split("\n")[:2] == ["ready", f"closed {len(sent)}"]
    topic = {i: t for i, t, _ in TOPICS}
    want = {t: [] for _, t, _ in TOPICS}
    for cid, t, data in sent:  # per topic in the order sent (times rise per topic)
        want[topic[cid]].append((t + OFFSET_NS, data))

    msgs, summary = mcap_messages(bag)
    got: dict[str, list] = {}
    for tp, log, pub, seq, data in msgs:
        assert pub == log
        got.setdefault(tp, []).append((log, data))
        assert seq == len(got[tp])  # 1, 2, ... per channel
    assert {tp: got[tp] for tp in want} == want
    assert len(summary.chunk_indexes) >= 4
    assert summary.statistics.message_count == len(sent) + 1  # + /fluxdrive/settings
    assert chunk_times_sorted(bag)

    by_rosbags: dict[str, list] = {}
    for tp, _type, t, data in read_raw(bag):  # rosbags' reader
        by_rosbags.setdefault(tp, []).append((t, bytes(data)))
    assert {tp: by_rosbags[tp] for tp in want} == want
    meta = (bag / "metadata.yaml").read_text()
    assert f"message_count: {len(sent) + 1}" in meta


def test_bulk_writes_the_file_one_by_one_writes(tmp_path):
    """write_stream (bulk, cut into pipe-sized blocks) and BagWriter.write per message give
    the same MCAP file, byte for byte: chunks cut at the same messages, same order."""
    sent = sent_messages(300)
    bulk = tmp_path / "a" / "bag"
    assert write_stream(Pipe(stream(bulk, sent, flush_every=10**9))) == 0
    single = tmp_path / "b" / "bag"
    w = BagWriter(single, {}, epoch_offset_ns=OFFSET_NS)
    cids = {i: w.add_connection(t, ty) for i, t, ty in TOPICS}
    for cid, t, data in sent:
        w.write(cids[cid], t, data)
    w.close()
    (a,) = bulk.glob("*.mcap")
    (b,) = single.glob("*.mcap")
    assert a.read_bytes() == b.read_bytes()


def test_a_cut_stream_keeps_what_was_complete(tmp_path, capsys):
    """EOF inside a message (the recorder killed mid-write): everything before it is in the
    finalised bag, the cut message is not."""
    sent = sent_messages(50)
    bag = tmp_path / "bag"
    raw = stream(bag, sent, flush_every=10**9)[:-1]  # no end marker
    cut = raw[: len(raw) - len(sent[-1][2]) // 2]
    assert write_stream(Pipe(cut)) == 0
    msgs, _ = mcap_messages(bag)
    assert len(msgs) == 1 + len(sent) - 1
    assert (bag / "metadata.yaml").exists()
