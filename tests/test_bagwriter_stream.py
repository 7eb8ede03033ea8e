"""The recorder's bag writer (fluxdrive.io.bagwriter, MCAP built in bulk by
fluxdrive.io.mcapfile): what goes down the pipe comes back out of the bag message for message
-- same bytes, same log times -- in every reader (mcap's own, rosbags, the project's), however
the pipe cuts the stream; and the bulk path writes the very file that writing the same
messages one by one does.  A block record (the recorder's messages of several topics, each as
they came) is laid out four seqs at a time: the file of the message records in that order."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
from fluxdrive.io import mcapfile
from fluxdrive.io.bagio import BagWriter, read_raw
from fluxdrive.io.bagwriter import BLOCK_PART, MSG_HDR, STEP_SEQS, pack_json, write_stream
from fluxdrive.io.messages import message_seq

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


def sample(seq: int, frame_id: bytes = b"drive", tail: bytes = b"") -> bytes:
    """A per-sample message as the graph serialises it: CDR header, stamp (seq x 100 us),
    frame_id, seq aligned to 8, graph_id, then `tail`."""
    sec, nsec = divmod(seq * 100_000, 10**9)
    fid = frame_id + b"\0"
    head = b"\x00\x01\x00\x00" + struct.pack("<iII", sec, nsec, len(fid)) + fid
    return head + bytes(-(len(head) - 4) % 8) + struct.pack("<QQ", seq, 7) + tail


def block_record(parts: list[tuple[int, list[bytes]]]) -> bytes:
    """The recorder's block record of these topics' messages (recorder id, messages)."""
    table, body = [struct.pack("<H", len(parts))], []
    for cid, datas in parts:
        size = len(datas[0]) if len({len(d) for d in datas}) == 1 else 0
        table.append(BLOCK_PART.pack(cid, len(datas), size))
        if not size:
            body.append(struct.pack(f"<{len(datas)}I", *map(len, datas)))
        body += datas
    raw = b"".join(table + body)
    return b"B" + struct.pack("<I", len(raw)) + raw


def in_step(parts: list[tuple[int, list[bytes]]]) -> list[tuple[int, bytes]]:
    """The order the bag gets: topics of several sizes or frame_id lengths first, as they
    came; the others by seq // STEP_SEQS, topic after topic within it (seqs going backwards
    in one of them: topic after topic)."""
    mixed = [p for p in parts if len({(len(d), d[12:16]) for d in p[1]}) > 1]
    even = [p for p in parts if p not in mixed]
    out = [(cid, d) for cid, datas in mixed for d in datas]
    seqs = [[message_seq(d) for d in datas] for _, datas in even]
    if any(q != sorted(q) for q in seqs):
        return out + [(cid, d) for cid, datas in even for d in datas]
    keyed = [
        ((q // STEP_SEQS, j), cid, d)
        for j, (cid, datas) in enumerate(even)
        for q, d in zip(seqs[j], datas, strict=True)
    ]
    return out + [(cid, d) for _, cid, d in sorted(keyed, key=lambda x: x[0])]


def block_parts(k0: int, n: int) -> list[tuple[int, list[bytes]]]:
    """A frame topic, an estimate topic lagging by 3 seqs with its own tail, a topic of two
    sizes and one whose frame_ids have two lengths (one size)."""
    mixed_ids = [sample(k, b"drive" if k % 2 else b"drivexx") for k in range(k0, k0 + n)]
    return [
        (1, [sample(k, tail=bytes(48)) for k in range(k0, k0 + n)]),
        (5, [sample(k, b"obs", b"flux" * 9) for k in range(k0 - 3, k0 + n - 3)]),
        (2, [sample(k, tail=b"x" * (k % 3 == 0) * 8) for k in range(k0 - 1, k0 + n - 1)]),
        (2, mixed_ids),
    ]


def records(bag: Path, body: list[bytes]) -> bytes:
    head = {"path": str(bag), "custom_data": {}, "epoch_offset_ns": OFFSET_NS}
    conns = [pack_json(b"C", {"id": i, "topic": t, "type": ty}) for i, t, ty in TOPICS]
    return b"".join([pack_json(b"H", head), *conns, *body, b"E"])


def message_record(cid: int, data: bytes) -> bytes:
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return MSG_HDR.pack(b"M", cid, sec * 10**9 + nsec, len(data)) + data


def test_a_block_is_the_messages_laid_out_in_step(tmp_path, capsys):
    """Blocks (among message and flush records, the pipe cutting them anywhere) give the
    very file that their messages one by one in step order give; seqs going backwards in a
    topic: topic after topic; a block cut by EOF is dropped whole."""
    blocks = [block_parts(10, 37), block_parts(47, 1), block_parts(48, 120)]
    blocks.append([(1, [sample(k) for k in (300, 299, 301)]), (5, [sample(298, b"obs")])])
    clock = message_record(2, struct.pack("<4siI", b"\x00\x01\x00\x00", 0, 5))
    body_b, body_m = [], []
    for parts in blocks:
        body_b += [block_record(parts), clock, b"F"]
        body_m += [message_record(cid, d) for cid, d in in_step(parts)] + [clock, b"F"]
    a, b = tmp_path / "a" / "bag", tmp_path / "b" / "bag"
    assert write_stream(Pipe(records(a, body_b))) == 0
    assert write_stream(Pipe(records(b, body_m))) == 0
    n = sum(len(d) for parts in blocks for _, d in parts) + len(blocks)
    assert capsys.readouterr().out.split("\n")[1] == f"closed {n}"
    ((fa,), (fb,)) = a.glob("*.mcap"), b.glob("*.mcap")
    assert fa.read_bytes() == fb.read_bytes()

    cut = tmp_path / "cut" / "bag"
    raw = records(cut, body_b[:3])[:-1]  # a whole block, then 100 bytes of the next one
    assert write_stream(Pipe(raw + block_record(blocks[1])[:100])) == 0
    msgs, _ = mcap_messages(cut)
    assert len(msgs) == 1 + sum(len(d) for _, d in blocks[0]) + 1  # settings, block, clock
