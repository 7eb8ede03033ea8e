"""`can-import` and `replay` against hostile files: the probe's cases (a capture of foreign or
huge IDs only said 'strides is incompatible ...' without the file; a truncated .blf imported
with exit 0 and no word of it) and a derandomized hypothesis fuzz over mutated captures
(.log text, .blf bytes) and mutated bags.  The property: the import or the replay succeeds,
or raises its one refusal (CaptureError / BagError, one line naming the file) -- never
another exception (time is not asserted: HANG_GUARD_S only ends a hung import)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest
from fluxdrive.can.canlog import CaptureError
from fluxdrive.io.bagio import BagError, read_run_bag
from fluxdrive.io.canimport import import_capture
from fluxdrive.replay.lab import parse_variant, replay_bag
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BLF = ROOT / "bags" / "samples" / "emulator_2pct_start_1s.blf"
# not a speed bound: an import still running after this long is hung (a runaway -- a huge
# allocation, a loop -- took minutes)
HANG_GUARD_S = 120.0
N_MSGS = 120  # CAN frames in the fuzzed captures
FUZZ = dict(
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _messages(n: int = N_MSGS) -> list[can.Message]:
    with can.LogReader(str(SAMPLE_BLF)) as r:
        out = []
        for m in r:
            out.append(m)
            if len(out) >= n:
                return out
    return out


def _write(path: Path, msgs: list[can.Message]) -> Path:
    from fluxdrive.can.canlog import open_writer

    w = open_writer(path)
    for m in msgs:
        w.on_message_received(m)
    w.stop()
    return path


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


# ----------------------------------------------------------------- the probe's cases
@pytest.mark.parametrize(
    "lines",
    [
        "(1.000000) can0 1FFFFFFF#DEADBEEF\n(1.001000) can0 123#0011\n",
        "(1.000000) can0 7FF#00\n(1.001000) can0 FFFFFFFFFFFFFFFFFFFFFFFFF#0011223344556677\n",
    ],
    ids=["foreign_ids", "huge_ids"],
)
def test_capture_without_sample_frames_is_one_line(tmp_path, lines):
    log = tmp_path / "foreign.log"
    log.write_text(lines)
    r = _cli("can-import", str(log), "--out", str(tmp_path / "bag"))
    err = r.stderr.strip()
    print(err)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(err.splitlines()) == 1
    assert err.startswith(f"can-import: {log}: none of its") and "other IDs" in err
    assert not (tmp_path / "bag").exists()


def test_truncated_blf_says_so_and_exits_1(tmp_path):
    cut = tmp_path / "cut.blf"
    data = SAMPLE_BLF.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    r = _cli("can-import", str(cut), "--out", str(tmp_path / "bag"))
    warn = [ln for ln in r.stderr.splitlines() if "WARNING" in ln]
    print(r.stderr.strip())
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert len(warn) == 1 and f"{cut}: truncated: {len(data) // 2} of the {len(data)}" in warn[0]
    rb = read_run_bag(tmp_path / "bag")  # the frames before the cut, and the bag says so
    assert len(rb.frames) > 1000
    assert "truncated" in rb.meta["can_import"]["truncated"]


# --------------------------------------------------------------------------- the fuzz
_LINE_TOKENS = [
    *"()# .\n",
    "can0 ",
    "080",
    "100",
    "7FF",
    "1FFFFFFF",
    "FFFFFFFFFFFFFFFFFFFF",
    "##1",
    "##0",
    "R",
    "00",
    "FF",
    "DEADBEEF" * 8,
    "1.000000",
    "-1e300",
    "nan",
]
_LINE = st.lists(st.sampled_from(_LINE_TOKENS), max_size=12).map("".join)


def _expect_refusal_or_ok(fn, path: Path) -> None:
    t0 = time.perf_counter()
    try:
        fn()
    except (CaptureError, BagError) as exc:
        msg = str(exc)
        assert "\n" not in msg and path.name in msg, msg
    finally:
        dt = time.perf_counter() - t0
        assert dt < HANG_GUARD_S, f"{dt:.1f} s for one file: hung"


def test_fuzz_can_import_text_capture(tmp_path):
    base = _write(tmp_path / "base.log", _messages()).read_text().splitlines(keepends=True)
    path = tmp_path / "fuzz.log"
    n = [0]

    @settings(max_examples=100, **FUZZ)
    @given(
        edits=st.lists(st.tuples(st.integers(0, len(base) - 1), _LINE), max_size=6),
        cut=st.integers(0, len(base)),
    )
    def run(edits: list[tuple[int, str]], cut: int) -> None:
        lines = list(base)
        for i, text in edits:
            lines[i] = text + "\n"
        path.write_text("".join(lines[: max(cut, len(lines) - 3)] if cut else lines))
        out = tmp_path / f"bag{n[0]}"
        n[0] += 1
        _expect_refusal_or_ok(lambda: import_capture(path, out), path)
        shutil.rmtree(out, ignore_errors=True)

    run()


def test_relative_clock_capture_gets_sample_time(tmp_path):
    """A capture whose clock is not an epoch time (a relative-time logger, or a .blf whose header
    time was zeroed: its frames land before 1970, which the fuzz found as an mcap struct.error
    traceback) imports with bag time = sample time, never a negative log time."""
    from fluxdrive.io.bagio import read_run_bag

    msgs = _messages()
    t0 = msgs[0].timestamp
    for m in msgs:
        m.timestamp -= t0 + 5.0  # the first frame 5 s before the epoch
    bag = tmp_path / "bag"
    import_capture(_write(tmp_path / "rel.log", msgs), bag)
    run = read_run_bag(bag)
    assert run.meta["can_import"]["source"].endswith("rel.log")
    from mcap.reader import make_reader

    with open(next(bag.glob("*.mcap")), "rb") as fh:
        times = [m.log_time for _, _, m in make_reader(fh).iter_messages()]
    assert times and min(times) >= 0 and times == sorted(times)


def test_fuzz_can_import_blf_bytes(tmp_path):
    base = _write(tmp_path / "base.blf", _messages()).read_bytes()
    path = tmp_path / "fuzz.blf"
    n = [0]

    @settings(max_examples=150, **FUZZ)
    @given(
        edits=st.lists(st.tuples(st.integers(0, len(base) - 1), st.integers(0, 255)), max_size=8),
        cut=st.integers(0, len(base)),
    )
    def run(edits: list[tuple[int, int]], cut: int) -> None:
        data = bytearray(base)
        for i, b in edits:
            data[i] = b
        path.write_bytes(bytes(data[:cut] if cut % 3 == 0 else data))
        out = tmp_path / f"bag{n[0]}"
        n[0] += 1
        _expect_refusal_or_ok(lambda: import_capture(path, out), path)
        shutil.rmtree(out, ignore_errors=True)

    run()


def test_fuzz_replay_mutated_bag(tmp_path):
    """A small bag (imported from the capture) with bytes of its .mcap or its metadata
    changed: replayed through the paper observer, or refused in one line."""
    src = tmp_path / "src_bag"
    import_capture(_write(tmp_path / "base.blf", _messages(600)), src)
    mcap = next(src.glob("*.mcap"))
    base_mcap, base_meta = mcap.read_bytes(), (src / "metadata.yaml").read_bytes()
    variants = [parse_variant("paper")]
    replay_bag(read_run_bag(src), variants)  # the unchanged bag replays (and compiles)
    bag = tmp_path / "bag"

    @settings(max_examples=60, **FUZZ)
    @given(
        edits=st.lists(
            st.tuples(st.integers(0, len(base_mcap) - 1), st.integers(0, 255)), max_size=6
        ),
        meta_edits=st.lists(
            st.tuples(st.integers(0, len(base_meta) - 1), st.integers(32, 126)), max_size=3
        ),
        cut=st.integers(0, len(base_mcap)),
    )
    def run(edits: list[tuple[int, int]], meta_edits: list[tuple[int, int]], cut: int) -> None:
        shutil.rmtree(bag, ignore_errors=True)
        bag.mkdir()
        data, meta = bytearray(base_mcap), bytearray(base_meta)
        for i, b in edits:
            data[i] = b
        for i, b in meta_edits:
            meta[i] = b
        (bag / mcap.name).write_bytes(bytes(data[:cut] if cut % 4 == 0 else data))
        (bag / "metadata.yaml").write_bytes(bytes(meta))
        _expect_refusal_or_ok(lambda: replay_bag(read_run_bag(bag), variants), bag)

    run()
