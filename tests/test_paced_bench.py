"""The paced bench (`./fluxdrive benchmark bench --paced`, fluxdrive.can.paced): the drive and
the host's hot path in processes of their own over udp_multicast, a busy loop beside them;
and the pieces it rests on (fluxdrive.can.realtime, the HOST_REF angle on the wire). The
figures are the benchmark's; these tests check that it runs and what it reports, not how
fast."""

from __future__ import annotations

import gc
import json
import math
import subprocess
import sys

import can
import pytest
from fluxdrive.can.bridge import BridgeConfig, CanBridge, bus_factory_from_params
from fluxdrive.can.loop import new_virtual_channel
from fluxdrive.can.protocol import ID_HOST_REF, get_protocol
from fluxdrive.can.realtime import GcPause, HotPath, enter_realtime
from fluxdrive.core.paths import ROOT

FIELDS = (
    "samples",
    "references",
    "late_beyond_timeout",
    "unanswered",
    "reference_timeout_ms",
    "latency_p50_us",
    "latency_p99_us",
    "latency_max_us",
    "drive_missed_periods",
    "host_realtime",
    "drive_realtime",
    "settings",
    "machine",
)


def test_paced_mode_runs_and_reports_its_fields(tmp_path):
    """A few seconds of the paced bench through the command: the last stdout line is the
    record, the same as the file written; every sample the drive sent is counted as a
    reference, unanswered or late, and at D = 4 a sample comes every 4th period."""
    out = tmp_path / "paced.json"
    cmd = [sys.executable, "-m", "fluxdrive.cli", "benchmark", "bench", "--paced"]
    cmd += ["--minutes", "0.05", "--busy-cores", "1", "--out", str(out)]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    rec = json.loads(p.stdout.strip().splitlines()[-1])
    assert rec == json.loads(out.read_text())
    for key in FIELDS:
        assert key in rec, key
    assert rec["settings"]["decimation"] == 4 and rec["settings"]["busy_cores"] == 1
    assert rec["periods"] == round(0.05 * 60 * 1e4)  # 3 s at the card's 10 kHz
    assert rec["samples"] == rec["periods"] // 4
    assert rec["references"] + rec["unanswered"] == rec["samples"]
    assert 0 <= rec["late_beyond_timeout"] <= rec["references"]
    assert rec["reference_timeout_ms"] == 10.0
    assert rec["latency_p50_us"] <= rec["latency_p99_us"] <= rec["latency_max_us"]
    assert "[bench paced]" in p.stderr  # the progress/settings lines


def test_bad_paced_option_is_one_line():
    cmd = [sys.executable, "-m", "fluxdrive.cli", "benchmark", "bench", "--paced"]
    p = subprocess.run(
        [*cmd, "--priority", "120"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 2
    assert "--priority" in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1


def test_gc_pause_keeps_collection_off_until_asked_and_restores_it():
    assert gc.isenabled()
    with GcPause(every_s=0.0) as pause:
        assert not gc.isenabled()
        assert gc.get_freeze_count() > 0
        pause.collect_young()
        assert pause.collections == 1 and not gc.isenabled()
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_realtime_in_a_thread_says_what_it_got():
    """Whatever this machine permits: the policy is what the thread runs with, and anything
    not applied is a note (never an exception)."""
    import os
    import threading

    got: dict = {}

    def body() -> None:
        rep = enter_realtime(10, cpu=min(os.sched_getaffinity(0)), lock_memory=False)
        got["rep"] = rep
        got["policy"] = os.sched_getscheduler(0)

    t = threading.Thread(target=body)
    t.start()
    t.join()
    rep = got["rep"]
    assert (got["policy"] == os.SCHED_FIFO) == rep.realtime
    assert rep.realtime or any("SCHED_FIFO" in n for n in rep.notes)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # only that thread
    with pytest.raises(ValueError, match="1..99"):
        enter_realtime(100)
    with HotPath(priority=0) as hot:
        assert not hot.report.realtime and hot.report.notes


@pytest.mark.parametrize("theta", [-1e-12, 2 * math.pi - 1e-6, 2 * math.pi, 4 * math.pi])
def test_reference_angle_next_to_2pi_goes_out_as_zero(theta):
    """An angle within half a step (2 pi / 65536) below 2 pi is the angle 0: it goes out as
    0 rather than as a raw value one past the signal's top (the encoder refused it)."""
    ch = new_virtual_channel("theta")
    rx = can.Bus(interface="virtual", channel=ch, fd=True)
    br = CanBridge(bus_factory_from_params("virtual", ch), BridgeConfig(control_split=True))
    br.connect()
    try:
        assert br.send_reference(3, 1.0, 2.0, theta, 100.0, False)
        msg = rx.recv(timeout=5.0)
        while msg is not None and msg.arbitration_id != ID_HOST_REF:
            msg = rx.recv(timeout=5.0)
        assert msg is not None
        d = get_protocol().decode(ID_HOST_REF, bytes(msg.data))
        assert d["ref_theta"] == pytest.approx(0.0, abs=1e-12)
        assert d["ref_id"] == pytest.approx(1.0, abs=1e-3)
    finally:
        br.shutdown()
        rx.shutdown()


_NODE_SCRIPT = r"""
import gc, json, os, sys, time
import rclpy
from rclpy.parameter import Parameter
from bench_bridge.bridge_node import BenchBridgeNode

rclpy.init()
node = BenchBridgeNode(parameter_overrides=[
    Parameter("channel", value=sys.argv[1]), Parameter("realtime_priority", value=10)])
rep = node._hot.report
end = time.monotonic() + 60.0
while not ((rep.realtime or rep.notes) and not gc.isenabled()) and time.monotonic() < end:
    time.sleep(0.01)
    rep = node._hot.report
out = {"policy": os.sched_getscheduler(node._thread.native_id), "realtime": rep.realtime,
       "notes": rep.notes, "gc_enabled": gc.isenabled(), "line": rep.line()}
node.destroy_node()
rclpy.shutdown()
print(json.dumps(out))
"""


def test_the_bridge_node_runs_its_can_thread_on_the_hot_path():
    """The product path: bench_bridge with `realtime_priority` runs its CAN thread in the
    same HotPath as the paced benchmark's host -- SCHED_FIFO where permitted (else a note
    saying why), the garbage collector off while it runs. In a process of its own (the
    memory lock is the process's)."""
    import os

    from ros_domains import domain

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain(77)))
    p = subprocess.run(
        [sys.executable, "-c", _NODE_SCRIPT, new_virtual_channel("rt-node")],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert (got["policy"] == os.SCHED_FIFO) == got["realtime"]
    assert got["realtime"] or any("SCHED_FIFO 10 refused" in n for n in got["notes"])
    assert not got["gc_enabled"]
    if got["realtime"]:
        assert "hot path: SCHED_FIFO 10" in p.stderr  # the node's log line
