"""A shadow observer in blocks (block_frames > 1) publishes exactly the estimates it would
publish frame by frame -- also when a block holds a bad frame, a repeated one and a gap,
which it re-runs frame by frame from the state before the block (same counts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("flux_observer_node")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")


def _frames() -> list[bytes]:
    """300 frames of the demo scenario's start, as the plant sends them, with frame 100
    not finite, frame 150 sent twice and frame 200 missing."""
    from fluxdrive.drive.plant import FR_IA
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive.io.messages import FrameWire, Stamp

    sc = load_scenario(SCENARIO)
    sc.duration_s = 0.03
    rows = run_scenario(sc, progress=False).frames
    fw, stamp = FrameWire(), Stamp(sc.machine.ts_s)
    out = []
    for k, row in enumerate(rows):
        if k == 200:
            continue
        row = row.copy()
        if k == 100:
            row[FR_IA] = np.nan
        out.append(fw.pack(row, *stamp(k)))
        if k == 150:
            out.append(out[-1])
    return out


def test_blocks_publish_the_per_frame_estimates(monkeypatch):
    from flux_observer_node.node import ObserverNode
    from rclpy.parameter import Parameter

    monkeypatch.setenv("FLUXDRIVE_INTRA_PROCESS", "0")  # the nodes' own publishers only
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain(29))
    frames = _frames()
    sent: dict[int, list[bytes]] = {}
    counts = {}
    try:
        for block in (1, 64):
            node = ObserverNode(
                f"emf_measured_{block}",
                namespace="/obs",
                context=ctx,
                parameter_overrides=[
                    Parameter("scenario", value=SCENARIO),
                    Parameter("observer", value="emf_measured"),
                    Parameter("block_frames", value=block),
                ],
            )
            out: list[bytes] = []
            node.pub.publish = out.append  # what the node hands its publisher, in order

            def publish_row(rc, row, seq, xf=0, out=out, stamp=node.stamp):
                out.append(rc.pack(row, seq, *stamp(seq), xf))  # the message of the row

            node.pub.publish_row = publish_row
            node.pub.publish_block = out.extend  # (a block: its messages in a row)
            for data in frames:
                node._on_frame(data)
            node._flush()  # the end of the run (done / stop) flushes what is left
            sent[block] = out
            counts[block] = dict(node.counts.values)
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    assert len(sent[1]) == len(frames)
    assert sent[64] == sent[1]  # the same bytes: every estimate bit for bit, same order
    assert counts[64] == counts[1]
    assert counts[1]["bad_samples"] >= 1 and counts[1]["repeated_or_backwards"] >= 1
    assert counts[1]["missing"] >= 1


def test_frames_unpacked_as_a_block_equal_one_by_one():
    from fluxdrive.drive.plant import FR_N
    from fluxdrive.io.messages import FrameWire

    frames = _frames()
    fw = FrameWire()
    block = np.zeros((len(frames), FR_N))
    seqs = fw.unpack_block(frames, block)
    assert seqs is not None  # one publisher's frames: one layout, one numpy pass
    one = np.zeros((len(frames), FR_N))
    assert seqs == [fw.unpack(d, one[i]) for i, d in enumerate(frames)]
    assert np.array_equal(block, one, equal_nan=True)


def test_shadows_share_one_unpacked_block():
    """The shadows of a process each get their own list of the same frames: the first
    unpacks them, the others take its rows; other frames are unpacked anew."""
    from flux_observer_node.node import FrameBlock
    from fluxdrive.drive.observers import frame_limits
    from fluxdrive.drive.plant import FR_N
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.io.messages import FrameWire

    frames = _frames()
    fw = FrameWire()
    first = FrameBlock.of(list(frames[:64]), fw)
    assert FrameBlock.of(list(frames[:64]), fw) is first  # another reader, the same block
    one = np.zeros((64, FR_N))
    seqs = [fw.unpack(d, one[i]) for i, d in enumerate(frames[:64])]
    assert np.array_equal(first.rows, one, equal_nan=True)
    assert first.seqs.tolist() == seqs and first.last_seq == max(seqs)
    lim = frame_limits(load_scenario(SCENARIO).machine)
    assert not first.out_of_range(lim)
    later = FrameBlock.of(list(frames[64:128]), fw)
    assert later is not first and later.seqs.tolist() == list(range(64, 128))
    assert FrameBlock.of(list(frames[64:128]), fw) is later


def test_shadows_share_one_reader_on_the_bus():
    """Subscriptions that share a reader (Bus.shared_reader: the shadows' frames) have their
    messages collected once, and each block goes to each of them, in publish order."""
    from types import SimpleNamespace

    from fluxdrive_ros.intra import Bus

    bus = Bus()
    bus.timer = object()  # no block timer (it needs a node): blocks go by size here
    got: dict[str, list] = {"a": [], "b": [], "solo": []}
    for name in ("a", "b"):
        reader = bus.shared_reader(("/f", 7, 3), got[name].append, 3)
        bus.add_subscription(
            SimpleNamespace(topic="/f", block=reader, block_tag=None, graph_id=7, callback=None)
        )
    solo = bus.shared_reader(("/f", 7, 2), got["solo"].append, 2)  # another block size
    bus.add_subscription(
        SimpleNamespace(topic="/f", block=solo, block_tag=None, graph_id=7, callback=None)
    )
    assert len(bus.targets_of("/f", 7)[0]) == 2  # one slot per reader
    for i in range(6):
        bus.post("/f", bytes([i]), 7)
    while bus.queue:  # what the executor's drain does
        cbs, data = bus.queue.popleft()
        for cb in cbs:
            cb(data)
    blocks = [[(None, [b"\x00", b"\x01", b"\x02"])], [(None, [b"\x03", b"\x04", b"\x05"])]]
    assert got["a"] == got["b"] == blocks
    assert [d for parts in got["solo"] for _, ds in parts for d in ds] == [
        bytes([i]) for i in range(6)
    ]
