"""The recorder's block path (fluxdrive_bringup.record.recorder._TopicBlock): a block's
record part -- each topic's messages joined, their sizes listed when they differ -- and its
bookkeeping once per topic: counts, the newest stamp, the last seq, and the seq gaps of a
topic with one message per period, the ones the per-message callback finds (a seq more than
one past the one before it; seqs going backwards are no gap)."""

from __future__ import annotations

import struct

import pytest
from fluxdrive.io.bagwriter import BLOCK_PART
from fluxdrive_bringup.record.recorder import _TopicBlock
from test_bagwriter_stream import sample


class Rec:
    """What _TopicBlock reads and writes of its RecorderNode."""

    def __init__(self):
        self.last_ts = 0
        self.counts = {"/drive/frame": 0}
        self.last_seq: dict[str, int] = {}
        self.gaps: list[tuple[int, int]] = []

    def _gap(self, topic: str, last: int, k: int) -> None:
        self.gaps.append((last, k))


def account(blocks: list[list[int]], frame_ids=(b"drive",)) -> Rec:
    rec = Rec()
    tag = _TopicBlock(rec, "/drive/frame", 3, every_period=True)  # type: ignore[arg-type]
    for seqs in blocks:
        datas = [sample(k, frame_ids[k % len(frame_ids)]) for k in seqs]
        tag.add(datas, [], [])
        tag.account(datas)
    return rec


@pytest.mark.parametrize(
    ("blocks", "gaps"),
    [
        ([[0, 1, 2], [3, 4], [5]], []),
        ([[0, 1, 2], [5, 6]], [(2, 5)]),
        ([[4, 5, 9, 10, 12]], [(5, 9), (10, 12)]),
        ([[0, 1], [2, 3, 2, 4, 7]], [(2, 4), (4, 7)]),  # backwards: no gap; on from there
        ([[0, 1], [2, 5, 4]], [(2, 5)]),  # as many as the seqs span, not in a row
        ([[10, 11], [0, 1, 2]], []),  # a new run from 0
    ],
)
def test_block_gaps_are_the_per_message_ones(blocks, gaps):
    rec = account(blocks)
    assert rec.gaps == gaps
    assert rec.last_seq == {"/drive/frame": blocks[-1][-1]}
    assert rec.counts["/drive/frame"] == sum(map(len, blocks))
    assert rec.last_ts == max(b[-1] for b in blocks) * 100_000  # each block's last stamp


def test_frame_ids_of_two_lengths_are_read_one_by_one():
    """Frame_ids of two lengths (one size): read one by one, the same gaps."""
    rec = account([[0, 1, 2, 3], [4, 5, 7]], frame_ids=(b"drive", b"drivexx"))
    assert rec.gaps == [(5, 7)]


def test_a_block_part_is_its_table_entry_sizes_and_messages():
    tag = _TopicBlock(Rec(), "/drive/frame", 3, every_period=False)  # type: ignore[arg-type]
    even = [sample(k) for k in range(3)]
    table, items = [], []
    tag.add(even, table, items)
    assert table == [BLOCK_PART.pack(3, 3, len(even[0]))] and items == [b"".join(even)]
    mixed = [sample(0), sample(1, tail=b"x" * 8)]
    table, items = [], []
    tag.add(mixed, table, items)
    sizes = struct.pack("<2I", len(mixed[0]), len(mixed[1]))
    assert table == [BLOCK_PART.pack(3, 2, 0)] and items == [sizes, b"".join(mixed)]
