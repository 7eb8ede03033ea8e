"""Bags and graph identity, without ROS: replay keeps the bag's own graph's messages (the
recorder's graph_id, else the id most frames carry) and names the others; a bag written
before messages carried graph_id decodes with the definitions it embeds."""

from __future__ import annotations

import numpy as np
import pytest
from fluxdrive.drive.plant import FR_SEQ
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.drive.sim import run_scenario
from fluxdrive.io import messages
from fluxdrive.io.bagio import BagWriter, decode_rows, read_run_bag, run_metadata
from fluxdrive.io.cdr import Codec, layout_type, msg_text
from fluxdrive.io.topics import FRAME, T_FRAME

MINE, OTHER = 7, 2**62 + 3


@pytest.fixture(scope="module")
def short_run():
    sc = load_scenario(scenario_path("paper_2pct_150load"))
    sc.duration_s = 0.02
    return run_scenario(sc, progress=False)


def _bag(path, res, settings_id: int | None):
    """Frames of graph MINE (the run) interleaved with a second graph's (other values,
    the same seqs) on one topic, as a recorder without the graph check would have it."""
    meta = run_metadata(res, 0, None, [])
    if settings_id is not None:
        meta["graph_id"] = settings_id
    mine = messages.FrameWire(graph_id=MINE)
    other = messages.FrameWire(graph_id=OTHER)
    with BagWriter(path, meta) as w:
        c = w.add_connection(FRAME, T_FRAME)
        for k, fr in enumerate(res.frames):
            t_ns = int(round(res.t[k] * 1e9))
            st = divmod(t_ns, 1_000_000_000)
            w.write(c, t_ns, mine.pack(fr, *st))
            if k % 4 == 0:
                w.write(c, t_ns + 1, other.pack(fr * 3.0 + 1.0, *st))
    return path


@pytest.mark.parametrize("settings_id", [MINE, None])
def test_replay_keeps_its_graph_and_names_the_other(tmp_path, short_run, settings_id):
    res = short_run
    rb = read_run_bag(_bag(tmp_path / "bag", res, settings_id))
    n_other = (len(res.frames) + 3) // 4
    assert np.array_equal(rb.frames, res.frames)  # exactly the run, nothing of the other
    assert not [p for p in rb.problems if "duplicate" in p]
    dropped = [p for p in rb.problems if "another graph" in p]
    assert len(dropped) == 1 and f"{n_other} messages of another graph dropped" in dropped[0]
    assert f"/drive/frame {n_other}" in dropped[0] and str(OTHER) in dropped[0]


def test_a_bag_from_before_graph_id_decodes_with_its_own_definition(short_run):
    # the recorded definition: today's PhaseFrame without the graph_id field
    old = "\n".join(
        ln
        for ln in msg_text(T_FRAME).splitlines()
        if not ln.startswith("uint64 graph_id") and "Graph identity" not in ln
    )
    lt = layout_type(T_FRAME, old + "\n================\nMSG: std_msgs/Header\n")
    assert lt != T_FRAME and layout_type(T_FRAME, msg_text(T_FRAME)) == T_FRAME
    codec = Codec(lt, {"header.frame_id": "drive"})
    assert "graph_id" not in codec.fields
    res = short_run
    raws = []
    for k, fr in enumerate(res.frames):
        v = {"header.stamp.sec": 0, "header.stamp.nanosec": k * 100_000, "seq": k}
        for path, col in messages.FRAME_MAP:
            v[path] = (
                bool(fr[col] > 0.5)
                if path == "pwm_enabled"
                else (int(fr[col]) if path == "status_flags" else fr[col])
            )
        raws.append(codec.pack(*[v[f] for f in codec.fields]))
    seq, rows, cols = decode_rows(T_FRAME, raws, definition=old)
    assert "graph_id" not in cols
    assert np.array_equal(seq, np.arange(len(res.frames)))
    assert np.array_equal(rows[:, FR_SEQ], res.frames[:, FR_SEQ])
    assert np.array_equal(rows, res.frames)


def test_live_replay_stamps_the_receiving_graphs_id(tmp_path, short_run):
    """`replay --live` into a graph: the frames carry that graph's id -- a today's bag's
    bytes patched in place, a bag from before graph_id re-encoded from its rows."""
    pytest.importorskip("rclpy")
    live = pytest.importorskip("fluxdrive_bringup.replay.live_replay")
    from fluxdrive.drive.scenario import REPO_ROOT
    from fluxdrive.io.bagio import write_run_bag
    from fluxdrive.io.messages import graph_id_of, row_codec

    new = read_run_bag(write_run_bag(short_run, tmp_path / "new"), keep_raw=True)
    old = read_run_bag(REPO_ROOT / "bags" / "samples" / "paper_2pct_150load", keep_raw=True)
    for bag in (new, old):
        out = live.for_graph(bag, MINE)
        assert len(out) == len(bag.frames)
        assert all(graph_id_of(b) == MINE for _, b in out)
        rows = np.zeros((len(out), bag.frames.shape[1]))
        for j, (_, b) in enumerate(out):
            row_codec(T_FRAME).unpack(b, rows[j])
        assert np.array_equal(rows, bag.frames)
    patched = live.for_graph(new, MINE)
    assert [len(b) for _, b in patched] == [len(b) for _, b in new.raw_frames]
