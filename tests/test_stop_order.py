"""A stop of the separate layout (one process per node, everything over DDS) ends with the
recorder holding every message the live nodes published before they stopped: each node
waits, as it stops, until the recorder has acknowledged what it sent; the launcher stops the
recorder last and hands it the nodes' published counts; the recorder finalises once it has
them (or their publishers are gone).  The bag is checked against each publisher's count.

The bug shows when the recorder lags the drive at the stop (a loaded machine): the test
makes the lag on purpose -- the recorder is SIGSTOPped at frame 1500 and the fault comes at
frame 2500 (a lag of about 1000 samples, well within the writers' history of 10 000) --
waiting for frame counts, never for a time.  Before the fix the bag lost 3218 duties,
controller states and estimates of 5906 this way (frames whole)."""

from __future__ import annotations

import io
import os
import signal
import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

from fluxdrive_bringup.launch.launcher import START_FRAMES  # noqa: E402
from test_process_faults import Run, graph_dict  # noqa: E402

SEPARATE = {n: n for n in ("plant", "flux_measured", "controller", "recorder")}
# topics of the nodes that live through the stop: every message they published is in the bag
ANSWERS = ("/drive/duty", "/drive/controller_state", "/obs/flux_measured/estimate")
LAG_FROM, FAULT_AT = 1500, 2500  # frames: recorder stopped, then the fault


def bag_seqs(bag: Path, topics: tuple[str, ...]) -> dict[str, list[int]]:
    """seq of every message on these topics, in bag order (definitions from the bag)."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list[int]] = {t: [] for t in topics}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic in out]
        for c, _, raw in reader.messages(connections=conns):
            out[c.topic].append(int(reader.deserialize(raw, c.msgtype).seq))
    return out


def lag_the_recorder(frames, pid_of, fault, running) -> threading.Thread:
    """In a thread: SIGSTOP the recorder once the plant is at LAG_FROM, then `fault()` at
    FAULT_AT (the launcher continues the recorder when it stops the graph).  It waits for
    the frames as long as the graph runs (kernels may compile first); a graph that ended
    before gets nothing (the test's checks then say what happened)."""

    def run() -> None:
        stop_recorder = lambda: os.kill(pid_of("recorder"), signal.SIGSTOP)  # noqa: E731
        for k, act in ((LAG_FROM, stop_recorder), (FAULT_AT, fault)):
            while frames() < k:
                if not running():
                    return
                time.sleep(0.02)
            act()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def check_whole(bag: Path, published: dict[str, int], topics: tuple[str, ...]) -> None:
    seqs = bag_seqs(bag, topics)
    got = {t: len(s) for t, s in seqs.items()}
    want = {t: published.get(t) for t in topics}
    print(f"bag {got}; published {want}")
    assert got == want
    for t in topics:
        assert seqs[t] == list(range(len(seqs[t]))), t  # 0..n-1, none twice, no gap


def test_sigint_of_the_launcher_separate_layout_bag_holds_every_message(tmp_path):
    """Ctrl-C (SIGINT) of the launcher while the recorder lags: the bag holds every frame,
    truth, duty, controller state and estimate each node published (the plant's last frame
    with the PWM off included), and the launcher says so."""
    from fluxdrive_bringup.launch.launcher import Launcher, parse_graph

    bag = tmp_path / "bag"
    graph = parse_graph(graph_dict(bag, duration_s=5.0, processes=SEPARATE), "stop.yaml")
    graph.domain_id = domain(30)
    out = io.StringIO()
    launcher = Launcher(graph, out=out, quiet=False, progress=False, log_dir=tmp_path / "logs")

    def frames() -> int:
        return launcher.progress[0] if launcher.progress else 0

    def pid_of(name: str) -> int:
        return next(p.process.pid for p in launcher.procs if p.name == name)

    def running() -> bool:
        return not (launcher.procs and all(p.done for p in launcher.procs))

    lag_the_recorder(frames, pid_of, lambda: os.kill(os.getpid(), signal.SIGINT), running)
    code = launcher.run(timeout=150)  # in the main thread: its SIGINT handler stops the graph
    text = out.getvalue()
    print("\n".join(ln for ln in text.splitlines() if "[launch]" in ln or "finalised" in ln))
    assert code == 128 + signal.SIGINT, text
    assert frames() >= FAULT_AT
    check_whole(bag, launcher.published, ("/drive/frame", "/drive/truth", *ANSWERS))
    assert f"bag {bag}: holds every message the nodes published" in text


def test_sigkill_of_the_plant_separate_layout_bag_holds_every_answer(tmp_path):
    """SIGKILL of the plant while the recorder lags: what the plant had not delivered dies
    with it, but the duties, controller states and estimates of every frame the controller
    and the observer answered are in the bag (each publisher's count), and the frames the
    bag holds are a gap-free prefix."""
    bag = tmp_path / "bag"
    run = Run(graph_dict(bag, duration_s=5.0, processes=SEPARATE), domain(31), tmp_path).start()
    kill_plant = lambda: os.kill(run.pid("plant"), signal.SIGKILL)  # noqa: E731
    lag_the_recorder(run.frames, run.pid, kill_plant, run.thread.is_alive)
    code = run.join()
    print("\n".join(ln for ln in run.lines if "[launch]" in ln or "finalised" in ln))
    assert code == 1
    assert "process 'plant' died (signal SIGKILL" in run.text()
    assert "/drive/frame" not in run.launcher.published  # the plant never said
    check_whole(bag, run.launcher.published, ANSWERS)
    frames = bag_seqs(bag, ("/drive/frame",))["/drive/frame"]
    # a gap-free prefix: what the recorder had received when it was stopped. How far it
    # reaches is the recorder's lag behind the plant at that moment (nothing in a lockstep
    # graph waits for its recorder: 1483 of the 1500 frames on a loaded machine), so the
    # only count is the start phase's, long done by then
    print(f"the bag holds frames 0..{len(frames) - 1}; the recorder was stopped at {LAG_FROM}")
    assert frames == list(range(len(frames))) and len(frames) >= START_FRAMES
