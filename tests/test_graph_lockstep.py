"""The ROS graph in lockstep: the same numbers as the in-process runner, every sample in the
bag, bags readable by rosbags and by the independent mcap reader, Ctrl-C finalises the bag.

Each test runs real processes (./fluxdrive launch / the run orchestration) on a ROS domain
of its own with discovery on localhost."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]


def _on_the_ideal_bench(path: Path) -> Path:
    """The scenario file on the ideal bench, written to a temporary directory: the closed-loop
    check below needs the sensorless start to hand over within the first second, which on the
    shipped scenario's non-ideal bench it does only later (docs/engine.md, "Non-ideal
    bench"); graph == in-process holds on either bench."""
    import tempfile

    from fluxdrive.drive.scenario import load_scenario, save_scenario

    out = Path(tempfile.mkdtemp(prefix="fluxdrive-ideal-bench-")) / path.name
    return save_scenario(load_scenario(path, overrides={"bench": {}}), out)


SCENARIO = _on_the_ideal_bench(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")


def reference(duration: float):
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive_bringup.launch.runs import shorten

    sc = load_scenario(SCENARIO)
    shorten(sc, duration)
    return run_scenario(sc, progress=False)


def graph_result(bag: Path, duration: float):
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive_bringup.launch.runs import result_from_bag

    return result_from_bag(bag, load_scenario(SCENARIO), duration)


def assert_same_run(res, ref):
    """Bit for bit: currents and every sample the graph recorded."""
    assert res.frames.shape == ref.frames.shape
    for name in ("frames", "truth", "est", "ctrl"):
        a, b = getattr(res, name), getattr(ref, name)
        assert not np.isnan(a).any(), f"{name}: samples missing in the bag"
        assert np.array_equal(a, b), (name, np.argwhere(a != b)[:5], np.nanmax(np.abs(a - b)))


@pytest.mark.parametrize("layout,duration", [("composed", 1.0), ("separate", 0.25)])
def test_graph_equals_in_process_runner(tmp_path, layout, duration):
    """(a) The lockstep graph (sensorless start: align, I-f, handover to the flux observer
    within the first second) gives the in-process runner's numbers exactly -- with the
    intra-process delivery of the composed layout and with everything over DDS."""
    from fluxdrive_bringup.launch.runs import run_graph

    bag = tmp_path / "bag"
    t0 = time.perf_counter()
    r = run_graph(
        SCENARIO,
        out=tmp_path / "run",
        bag=bag,
        layout=layout,
        duration_s=duration,
        domain_id=domain(12 if layout == "composed" else 13),
        quiet=True,
        timeout=240,
        progress=False,
    )
    assert r["code"] == 0, tmp_path / "run" / "logs"
    print(
        f"{layout}: {r['frames']} frames, lockstep RTF {r['lockstep_rtf']:.3f}, command "
        f"{time.perf_counter() - t0:.1f} s"
    )
    res, arr = graph_result(bag, duration)
    assert arr["n"] == int(round(duration * 1e4))
    assert all(v == 0 for v in arr["missing"].values()), arr["missing"]
    assert_same_run(res, reference(duration))
    if layout == "composed":
        from fluxdrive.drive.control import CO_MODE, MODE_CLOSED_LOOP

        # the run reached sensorless closed loop on the flux observer
        assert (res.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP).any()


def _bag_checks(bag: Path, complete_n: int | None = None) -> int:
    """The bag opens with rosbags' AnyReader (definitions from the bag itself, no typestore
    given) and with the independent mcap + mcap_ros2 reader; frames are seq 0..N-1 without a
    gap.  Returns N."""
    from rosbags.highlevel import AnyReader

    assert (bag / "metadata.yaml").exists()
    seqs = []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/frame"]
        assert conns and conns[0].msgtype == "flux_drive_msgs/msg/PhaseFrame"
        for conn, _, raw in reader.messages(connections=conns):
            seqs.append(reader.deserialize(raw, conn.msgtype).seq)
        topics = {c.topic: c.msgcount for c in reader.connections}
    n = len(seqs)
    assert seqs == list(range(n)), "frames missing or out of order in the bag"
    if complete_n is not None:
        assert n == complete_n
    for t in (
        "/drive/truth",
        "/drive/duty",
        "/drive/controller_state",
        "/obs/flux_measured/estimate",
    ):
        assert topics.get(t, 0) >= n - 3, (t, topics.get(t), n)

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    files = sorted(bag.glob("*.mcap"))
    assert len(files) == 1
    m_seqs = []
    with open(files[0], "rb") as fh:
        rd = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, _ch, _, msg in rd.iter_decoded_messages(topics=["/drive/frame"]):
            m_seqs.append(msg.seq)
            assert len(msg.i_abc) == 3
    assert m_seqs == seqs
    return n


def test_bag_every_frame_two_readers_and_replay_metadata(tmp_path):
    """(b) A run's bag holds every frame (count = last seq + 1) and every estimate; it opens
    with rosbags and with mcap/mcap_ros2; the replay lab (fluxdrive.io.bagio) reads it with the
    run's metadata and no problems."""
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive_bringup.launch.launcher import Launcher
    from fluxdrive_bringup.launch.runs import graph_for_scenario, shorten

    sc = load_scenario(SCENARIO)
    shorten(sc, 0.3)
    bag = tmp_path / "bag"
    g = graph_for_scenario(SCENARIO, sc, bag, "composed", 0.3, domain(14))
    launcher = Launcher(g, quiet=True, progress=False)
    assert launcher.run(timeout=120) == 0
    assert launcher.bags == [str(bag.resolve())]
    assert _bag_checks(bag, complete_n=3000) == 3000

    from fluxdrive.io.bagio import read_run_bag

    rb = read_run_bag(bag)
    assert rb.problems == []
    assert rb.meta["scenario"]["name"] == "paper_2pct_150load"
    assert sorted(rb.est) == sorted(sc.observers)
    assert rb.n == 3000


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_finalises_the_bag(tmp_path, sig):
    """(b) `./fluxdrive launch` on a long lockstep run, interrupted with SIGINT (or SIGTERM)
    mid-run: the launcher stops every node cleanly -- exit 130 (143), as a shell reports a
    stop -- and the bag is finalised and complete up to the last frame recorded."""
    bag = tmp_path / "bag"
    graph = {
        "name": "interrupted",
        "nodes": [
            {
                "name": "plant",
                "node": "plant",
                "process": "drive",
                "parameters": {
                    "scenario": str(SCENARIO),
                    "duration_s": 60.0,
                    "wait_frame_subscribers": 3,
                    "start_delay_s": 0.2,
                },
            },
            {
                "name": "flux_measured",
                "namespace": "/obs",
                "node": "observer",
                "process": "drive",
                "parameters": {"scenario": str(SCENARIO)},
            },
            {
                "name": "controller",
                "node": "controller",
                "process": "drive",
                "parameters": {"scenario": str(SCENARIO)},
            },
            {
                "name": "recorder",
                "node": "recorder",
                "process": "drive",
                "parameters": {"bag_dir": str(bag), "observers": ["flux_measured"]},
            },
        ],
    }
    gpath = tmp_path / "graph.yaml"
    gpath.write_text(yaml.safe_dump(graph))
    env = dict(os.environ)
    env.pop("ROS_DOMAIN_ID", None)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fluxdrive.cli",
            "launch",
            str(gpath),
            "--domain-id",
            str(domain(15)),
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end and proc.poll() is None:
        if any("starting" in ln and "[plant]" in ln for ln in list(lines)):
            break
        time.sleep(0.1)
    else:
        proc.kill()
        pytest.fail("the graph did not start:\n" + "".join(lines))
    # mid-run: a few chunks of the bag written (at 2 MB well past the 1000 frames asserted
    # below, however slowly a loaded machine runs the graph), not a fixed 2 s
    t_end = time.monotonic() + 120
    while not any(f.stat().st_size > 2_000_000 for f in bag.glob("*.mcap")):
        if proc.poll() is not None or time.monotonic() > t_end:
            proc.kill()
            pytest.fail("the graph wrote no 2 MB of its bag:\n" + "".join(lines))
        time.sleep(0.1)
    proc.send_signal(sig)
    try:
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(timeout=10)
    out = "".join(lines)
    assert proc.returncode == 128 + int(sig), out
    assert f"{sig.name}: stopping the graph" in out
    assert "finalised" in out
    n = _bag_checks(bag)
    assert 1000 < n < 600000, out  # interrupted mid-run


def test_tripped_run_records_the_fault(tmp_path):
    """A drive that trips at once (DC-bus over-voltage limit below the bus): the graph
    records the latched fault, its code survives the trip through ControllerState's text,
    and the whole run still equals the in-process runner."""
    from fluxdrive.drive.control import CO_EN, CO_FAULT, FAULT_OVERVOLTAGE
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive_bringup.launch.runs import result_from_bag, run_graph

    raw = yaml.safe_load(SCENARIO.read_text())
    raw.update(
        name="tripped",
        duration_s=0.1,
        steady_window_s=[0.05, 0.1],
        machine=str(ROOT / "config" / "machines" / "default_spm.yaml"),
    )
    raw["control"] = {**raw["control"], "vdc_max_v": 50.0}
    sp = tmp_path / "tripped.yaml"
    sp.write_text(yaml.safe_dump(raw))
    bag = tmp_path / "bag"
    r = run_graph(
        sp,
        out=tmp_path / "run",
        bag=bag,
        duration_s=0.1,
        domain_id=domain(16),
        quiet=True,
        timeout=120,
        progress=False,
    )
    assert r["code"] == 0
    res, arr = result_from_bag(bag, load_scenario(sp), 0.1)
    assert all(v == 0 for v in arr["missing"].values()), arr["missing"]
    assert (res.ctrl[:, CO_FAULT] == FAULT_OVERVOLTAGE).all()
    assert (res.ctrl[:, CO_EN] == 0.0).all()
    assert_same_run(res, run_scenario(load_scenario(sp), progress=False))
