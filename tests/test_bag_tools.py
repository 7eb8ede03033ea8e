"""Bags every MCAP tool opens, settings that survive conversion, CAN captures imported the
way the bridge hands them to the graph, and can-import's answers to bad captures."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fluxdrive.drive.scenario import REPO_ROOT, load_scenario, scenario_path
from fluxdrive.drive.sim import run_scenario
from fluxdrive.io.bagio import read_run_bag, write_run_bag

VENV_BIN = Path(sys.executable).parent
SAMPLES = REPO_ROOT / "bags" / "samples"


@pytest.fixture(scope="module")
def short_bag(tmp_path_factory):
    sc = load_scenario(scenario_path("paper_2pct_150load"))
    sc.duration_s = 0.05
    res = run_scenario(sc)
    path = tmp_path_factory.mktemp("bags") / "short"
    write_run_bag(res, path)
    return path, res


def mcap_file(bag: Path) -> Path:
    (f,) = bag.glob("*.mcap")
    return f


def check_mcap(bag: Path) -> dict[str, int]:
    """Open with the `mcap` library, decode every message with mcap-ros2-support, check the
    conventions (zstd chunks, log times on the epoch and ordered per chunk, sequence numbers
    per channel); returns messages per topic."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    counts: dict[str, int] = {}
    with mcap_file(bag).open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes
        assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}
        assert summary.statistics.message_start_time > 1_600_000_000 * 10**9  # not 1970
        last_seq: dict[int, int] = {}
        for _schema, channel, msg, decoded in reader.iter_decoded_messages(log_time_order=False):
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            assert msg.sequence == last_seq.get(channel.id, 0) + 1
            last_seq[channel.id] = msg.sequence
            assert msg.publish_time == msg.log_time
            if hasattr(decoded, "seq"):
                assert decoded.seq >= 0
        chans = summary.channels
        assert all("offered_qos_profiles" in c.metadata for c in chans.values())
        # rosbag2's MCAP storage (Jazzy) names each channel's type by its RIHS01 hash
        from fluxdrive.io.bagio import typestore

        store = typestore()
        for c in chans.values():
            schema = summary.schemas[c.schema_id].name
            assert c.metadata.get("topic_type_hash") == store.hash_rihs01(schema), c.topic
        # the bag spans its data: its first message (the settings) is at the first frame
        first_frame = min(
            m.log_time
            for _s, ch, m in reader.iter_messages(topics=["/drive/frame"], log_time_order=True)
        )
        assert summary.statistics.message_start_time == first_frame
        meta = {m.name for m in reader.iter_metadata()}
        assert {"rosbag2", "fluxdrive"} <= meta
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    with mcap_file(bag).open("rb") as fh:  # log times ordered inside every chunk
        for rec in StreamReader(fh, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                t = [m.log_time for m in breakup_chunk(rec) if isinstance(m, Message)]
                assert t == sorted(t)
    return counts


def doctor(bag: Path) -> str:
    """pymcap-cli doctor: an MCAP validator independent of the writer's library."""
    r = subprocess.run(
        [str(VENV_BIN / "pymcap-cli"), "doctor", str(mcap_file(bag))],
        capture_output=True,
        text=True,
        timeout=300,
        # its report is wrapped to the terminal's width, which without a terminal (an xdist
        # worker) is 80: one line per sentence, whatever runs the test
        env=dict(os.environ, COLUMNS="1000"),
    )
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "passed MCAP doctor" in out, out
    assert not re.search(r"\b[1-9][0-9,]* (warning|error)", out), out
    return out


def test_written_bag_opens_in_every_mcap_tool(short_bag):
    bag, res = short_bag
    counts = check_mcap(bag)
    assert counts["/drive/frame"] == len(res.t) and counts["/fluxdrive/settings"] == 1
    out = doctor(bag)
    assert "error" not in out.lower().replace("0 errors", ""), out
    info = (bag / "metadata.yaml").read_text()
    assert "ros_distro: jazzy" in info and "offered_qos_profiles: []" not in info
    b = read_run_bag(bag)
    assert b.problems == [] and b.meta["machine"]["name"]
    # header stamps stay sim time; the bag's times are sim time + the recorded offset
    assert b.t[0] == 0.0 and b.meta["epoch_offset_ns"] > 1_600_000_000 * 10**9


def test_shipped_samples_open_in_every_mcap_tool():
    for nm in ("paper_2pct_150load", "paper_6pct_stepload"):
        d = SAMPLES / nm
        assert not list(d.glob("*.zstd")), "file-compressed bag shipped"
        counts = check_mcap(d)
        assert counts["/drive/frame"] >= 10000


def test_converted_bag_replays_with_its_settings(short_bag, tmp_path):
    """rosbags-convert to rosbag1 and back keeps only messages: the settings come back
    from /fluxdrive/settings; a bag with no settings says so in one line."""
    bag, res = short_bag
    conv = VENV_BIN / "rosbags-convert"
    subprocess.run(
        [str(conv), "--src", str(bag), "--dst", str(tmp_path / "r1.bag")],
        check=True,
        capture_output=True,
        timeout=300,
    )
    subprocess.run(
        [str(conv), "--src", str(tmp_path / "r1.bag"), "--dst", str(tmp_path / "back")],
        check=True,
        capture_output=True,
        timeout=300,
    )
    assert "custom_data: null" in (tmp_path / "back" / "metadata.yaml").read_text()
    b = read_run_bag(tmp_path / "back")
    assert b.problems == [], b.problems
    assert b.meta["machine"] == read_run_bag(bag).meta["machine"]
    assert sorted(b.meta["observers"]) == sorted(res.names)
    from fluxdrive.replay.lab import expand_variants, replay_bag

    rr = replay_bag(b, expand_variants(["@recorded"], b))
    i = res.names.index("flux_measured")
    j = rr.names.index("flux_measured")
    assert np.array_equal(rr.est[j], res.est[i])  # same card, same configuration
    # no settings anywhere: one line says so
    subprocess.run(
        [
            str(conv),
            "--src",
            str(bag),
            "--dst",
            str(tmp_path / "bare"),
            "--exclude-topic",
            "/fluxdrive/settings",
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    bb = read_run_bag(tmp_path / "bare")
    assert any("no recorder settings" in p for p in bb.problems)


# ---------------------------------------------------------------- CAN capture import
@pytest.mark.parametrize("layout,d", [("fd", 4), ("classic", 8)])
def test_decimated_capture_replays_like_the_live_bridge_run(tmp_path, layout, d):
    from fluxdrive.can.loop import run_can_loop
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.io.canimport import import_capture
    from fluxdrive.replay.lab import expand_variants, replay_bag

    sc = load_scenario(scenario_path("can_2pct_decimated"))
    cap = tmp_path / "cap.log"
    live = run_can_loop(sc, 400 * d, layout=layout, decimation=d, log_path=str(cap))
    res = import_capture(cap, tmp_path / "bag", scenario="can_2pct_decimated")
    assert res["decimation"] == d and res["layout"] == layout and res["gaps"] == 0
    b = read_run_bag(tmp_path / "bag")
    assert b.problems == [], b.problems
    assert b.meta["can_import"]["decimation"] == d
    assert b.meta["can_import"]["sample_period_s"] == pytest.approx(d * sc.machine.ts_s)
    assert b.machine().ts_s == pytest.approx(d * sc.machine.ts_s)
    # frames carry the sample index j, stamped j D Ts: consecutive, the live run's
    assert np.array_equal(b.frames[:, FR_SEQ], live.seq_rx)
    assert np.allclose(np.diff(b.t), d * sc.machine.ts_s)
    rr = replay_bag(b, expand_variants(["@recorded"], b))
    for o, nm in enumerate(live.control_setup.names):
        assert np.array_equal(rr.est[rr.names.index(nm)], live.est[o]), nm


def _can_import(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "can-import", *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=str(REPO_ROOT),
    )


def _one_line(r: subprocess.CompletedProcess) -> str:
    assert r.returncode != 0, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    return r.stderr.strip()


def test_can_import_bad_captures_one_line(tmp_path):
    blf = tmp_path / "garbage.blf"
    blf.write_bytes(bytes(range(256)) * 8)
    err = _one_line(_can_import(str(blf), "--out", str(tmp_path / "b1")))
    assert "garbage.blf" in err and "BLF" in err
    empty = tmp_path / "empty.log"
    empty.write_text("")
    err = _one_line(_can_import(str(empty), "--out", str(tmp_path / "b2")))
    assert "empty.log" in err and "no CAN frames" in err
    assert not (tmp_path / "b1").exists() and not (tmp_path / "b2").exists()


def test_can_import_skips_and_counts_malformed_lines(tmp_path):
    from fluxdrive.can import canlog
    from fluxdrive.can import protocol as cp

    n = 2000
    f = np.zeros((n, len(cp.FRAME_FIELDS)))
    f[:, cp.FRAME_INDEX["vdc"]] = 72.0
    f[:, cp.FRAME_INDEX["pwm_enabled"]] = 1
    f[:, cp.FRAME_INDEX["seq"]] = np.arange(n)
    good = tmp_path / "good.log"
    canlog.write_capture(good, cp.frames_to_fd_payloads(f))
    lines = good.read_text().splitlines(keepends=True)
    bad_at = [500, 1500]  # 1-based line numbers of the damaged lines
    for ln in bad_at:
        lines[ln - 1] = "(17.5) can0 12#ZZ-not-hex\n"
    cap = tmp_path / "bad.log"
    cap.write_text("".join(lines))
    r = _can_import(str(cap), "--out", str(tmp_path / "bag"))
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "skipped 2 malformed line(s)" in r.stderr
    assert "bad.log:500:" in r.stderr and "bad.log:1500:" in r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["written"] == len(lines) - len(bad_at) - (len(lines) - n)
    assert read_run_bag(tmp_path / "bag").n == res["written"]


def test_interrupted_run_counts_the_bag(short_bag):
    from fluxdrive_bringup.launch.runs import interrupted_bag_note

    bag, res = short_bag
    assert f"holds {len(res.t)} frames" in interrupted_bag_note(bag)
    assert "not readable" in interrupted_bag_note(bag.parent / "nothing")
    shutil.rmtree(bag.parent / "nothing", ignore_errors=True)
