"""Hostile frames on the bus of `./fluxdrive bench --sil`: a probe on the bench's own
udp_multicast group and port sniffs 200 samples, sends one DBC-valid SAMPLE_FD 30 000
periods ahead of the stream (a jump), the 200 sniffed samples again three times (a
replay) and 20 000 foreign-id frames as fast as it can (a flood). The run still ends
normally: no traceback, every sample of every topic in the bag once (no duplicate, no
gap), the bridge's counts of what it dropped in /diagnostics and its last log line."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("msgpack")  # python-can's udp_multicast needs it
# the C drive paced against the graph over a CAN bus, and a timed flood: alone
pytestmark = pytest.mark.serial

from bench_harness import DURATION_S, D  # noqa: E402
from bench_harness import case as _case  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _bus_of(report: Path, proc: subprocess.Popen, timeout_s: float = 120.0) -> dict:
    """The bench's bus (group, port) from the graph it writes before it starts."""
    f = report / "graph.yaml"
    t_end = time.monotonic() + timeout_s
    cmd = None
    while cmd is None:  # until the file is there and written whole (the drive's node in it)
        assert proc.poll() is None and time.monotonic() < t_end, "the bench did not start"
        try:
            g = yaml.safe_load(f.read_text())
            cmd = next(n["cmd"] for n in g["nodes"] if n.get("name") == "drive")
        except (OSError, yaml.YAMLError, TypeError, KeyError, StopIteration):
            time.sleep(0.05)
    return {
        "interface": "udp_multicast",
        "channel": cmd[cmd.index("--channel") + 1],
        "port": int(cmd[cmd.index("--port") + 1]),
        "hop_limit": 0,
    }


def _attack(kw: dict, proc: subprocess.Popen) -> dict:
    """Sniff 200 samples, then jump, replay three times, flood; what was sent."""
    import can
    from fluxdrive.can.protocol import ID_SAMPLE_FD, get_protocol

    proto = get_protocol()
    bus = can.Bus(fd=True, **kw)
    sniffed: list[can.Message] = []
    try:
        t_end = time.monotonic() + 180.0
        while len(sniffed) < 200:
            assert proc.poll() is None and time.monotonic() < t_end, "no samples on the bus"
            m = bus.recv(0.1)
            if m is not None and m.arbitration_id == ID_SAMPLE_FD:
                sniffed.append(m)
        d = proto.decode("SAMPLE_FD", bytes(sniffed[-1].data))
        d["seq"] = (int(d["seq"]) + 30_000) % 65536
        jump = can.Message(
            arbitration_id=ID_SAMPLE_FD,
            is_extended_id=False,
            is_fd=True,
            bitrate_switch=True,
            data=proto.encode("SAMPLE_FD", d),
        )
        bus.send(jump)
        for _ in range(3):
            for m in sniffed:
                bus.send(m)
        foreign = can.Message(arbitration_id=0x555, is_extended_id=False, data=bytes(8))
        t0 = time.monotonic()
        for _ in range(20_000):
            bus.send(foreign)
        flood_s = time.monotonic() - t0
    finally:
        bus.shutdown()
    return {"flood_s": flood_s}


def test_bench_sil_survives_jump_replay_and_flood(tmp_path):
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.io.bagio import read_raw, typestore
    from fluxdrive_bringup.measure.sil import result_from_sil_bag

    sp = _case(tmp_path / "sil_2pct_split.yaml")
    bag = tmp_path / "bag"
    report = Path(str(bag) + "-report")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen(
        [sys.executable, "-m", "fluxdrive.cli", "bench", "--sil", str(sp), "--mode", "split"]
        + ["--decimation", str(D), "--bag", str(bag), "--domain-id", str(domain(61)), "--quiet"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        sent = _attack(_bus_of(report, proc), proc)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    print(out[-3000:])
    print(f"flood: 20000 foreign frames in {sent['flood_s']:.2f} s")
    assert "Traceback" not in out
    assert proc.returncode == 0, out[-3000:]
    assert "every sample of every topic present" in out

    sc = load_scenario(sp)
    n = int(round(DURATION_S / sc.machine.ts_s)) // D
    _, arr = result_from_sil_bag(bag, sc, D, report / "truth.npy")
    seqs = arr["frames"][:, FR_SEQ]
    assert arr["n"] == n and np.array_equal(seqs, np.arange(n)), (arr["n"], n)
    # every frame once in the bag: no duplicate, no gap (the seq the graph saw never jumped)
    ts = typestore()
    frames = [
        ts.deserialize_cdr(raw, mt).seq
        for topic, mt, _, raw in read_raw(bag, lambda t: t == "/drive/frame")
        if topic == "/drive/frame"
    ]
    assert sorted(frames) == list(range(n)) and len(set(frames)) == len(frames)
    # what the bridge dropped: in its last log line and on /diagnostics
    log = (report / "logs" / "bench_bridge.log").read_text()
    line = next(ln for ln in log.splitlines() if "CAN link:" in ln)
    print(line)
    assert "1 jumps" in line and "600 duplicates" in line, line
    # the flood's foreign frames: counted, not passed on; udp_multicast (a datagram each)
    # may lose some of them at the socket, never a sample (all checked above)
    m = re.search(r"(\d+) frames of other IDs", line)
    assert m and 0 < int(m.group(1)) <= 20000, line
    # ... and in the bag's metadata, from its last /diagnostics report
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    link = json.loads(info["custom_data"]["fluxdrive_can_link"])
    assert link["seq_jumps"] == 1 and link["seq_duplicates"] == 600, link
    assert link["frames_out"] >= 200 and link["seq_gaps"] == 0, link
    assert "[bench] CAN link (the bridge's last report): frames_out" in out
