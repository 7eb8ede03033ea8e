"""`bag recover` on a file cut anywhere in a record: the complete chunks before the cut come
back, frames without a gap (the sample starts at a seq past 0), and the reason names the cut
(not a parser's message), whether it falls in a record's opcode, its length field or its body."""

from __future__ import annotations

import shutil

import pytest
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive.io.bagio import read_run_bag
from fluxdrive.io.bagrecover import recover

SAMPLE = REPO_ROOT / "bags" / "samples" / "paper_2pct_150load"


def record_starts(mcap) -> list[tuple[str, int]]:
    """(record type, byte offset where it starts) of every record of a whole MCAP file."""
    from mcap.stream_reader import StreamReader

    out = []
    with open(mcap, "rb") as fh:
        records = StreamReader(fh, emit_chunks=True).records
        start = fh.tell()
        for r in records:
            out.append((type(r).__name__, start if out else 8))  # after the magic
            start = fh.tell()
    return out


@pytest.fixture(scope="module")
def sample_mcap():
    (mcap,) = SAMPLE.glob("*.mcap")
    return mcap


# bytes of the second chunk left: its opcode only, part of its 8-byte length, the whole
# length, part of its body
@pytest.mark.parametrize("into", [1, 5, 9, 40])
def test_a_cut_inside_a_record_keeps_the_chunks_before_it(sample_mcap, tmp_path, into):
    chunks = [at for kind, at in record_starts(sample_mcap) if kind == "Chunk"]
    assert len(chunks) >= 3
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "cut.mcap").write_bytes(sample_mcap.read_bytes()[: chunks[1] + into])
    rec = recover(cut, tmp_path / "out")
    assert rec.chunks == 1 and rec.bytes_read == chunks[1]
    assert rec.stop_reason == (
        f"stopped at byte {chunks[1]}: the file ends inside a record (the writer stopped there)"
    )
    first, last, gaps = rec.frame_seqs or (0, -1, -1)
    frames = read_run_bag(tmp_path / "out").frames
    assert gaps == 0 and len(frames) == last - first + 1 == rec.counts["/drive/frame"] > 0


def test_a_cut_between_records_is_data_without_summary(sample_mcap, tmp_path):
    chunks = [at for kind, at in record_starts(sample_mcap) if kind == "Chunk"]
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "cut.mcap").write_bytes(sample_mcap.read_bytes()[: chunks[2]])
    rec = recover(cut, tmp_path / "out")
    assert rec.chunks == 2 and rec.stop_reason.endswith(
        "the data ends there, without the summary (not finalised)"
    )
    shutil.rmtree(tmp_path / "out")
