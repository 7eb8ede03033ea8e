"""Bad input to the graph commands answered in one line, a non-zero exit and no traceback:
`param get`/`param set` of a parameter the node does not have, ROS 2 security enforced
without a keystore (topic list, param, launch, run), `launch`/`run` on a ROS domain other
nodes live on (refused, naming them); and the first `topic list` shows every topic of a
node that has just started (it waits for discovery to settle)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")

ROOT = Path(__file__).resolve().parents[1]


def _domain() -> int:
    return domain(23)


def fluxdrive(*args: str, env_extra: dict | None = None, timeout: float = 90.0):
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(_domain()),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        **(env_extra or {}),
    }
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _one_line(r: subprocess.CompletedProcess) -> str:
    err = r.stderr.strip()
    assert "Traceback" not in r.stderr + r.stdout, r.stderr
    assert len(err.splitlines()) == 1, err
    return err


class ProbeNode:
    """A node with a parameter and a few publishers, spun in a thread (own context)."""

    def __init__(self, topics=("/probe/a", "/probe/b", "/probe/c")):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import UInt64

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=_domain())
        self.node = rclpy.create_node("harden_probe", context=self.ctx)
        self.node.declare_parameter("gain", 1.5)
        self.pubs = [self.node.create_publisher(UInt64, t, 1) for t in topics]
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while self.ctx.ok():
            try:
                self.ex.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - shutting down
                return

    def close(self) -> None:
        self.ctx.try_shutdown()
        self.thread.join(5)


@pytest.fixture
def probe():
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    p = ProbeNode()
    yield p
    p.close()


def test_first_topic_list_shows_every_topic_and_unknown_parameters_are_one_line(probe, tmp_path):
    r = fluxdrive("topic", "list")  # at once: discovery of the new node still going on
    assert r.returncode == 0, r.stderr
    for t in ("/probe/a", "/probe/b", "/probe/c"):
        assert t in r.stdout, r.stdout
    r = fluxdrive("param", "get", "/harden_probe", "gain")
    assert r.returncode == 0 and "gain: 1.5" in r.stdout, r.stderr
    r = fluxdrive("param", "get", "/harden_probe", "no_such_param")
    assert r.returncode == 1
    assert _one_line(r) == "/harden_probe has no parameter 'no_such_param'"
    r = fluxdrive("param", "set", "/harden_probe", "no_such_param", "2.0")
    assert r.returncode == 1
    assert "has no parameter 'no_such_param'" in _one_line(r)
    # a second graph on a domain in use is refused, naming what lives there
    for cmd in (
        ["launch", "sim_lockstep", "--domain-id", str(_domain())],
        [
            "run",
            "paper_2pct_150load",
            "--duration",
            "0.1",
            "--out",
            str(tmp_path / "out"),
            "--bag",
            str(tmp_path / "bag"),
        ],
    ):
        r = fluxdrive(*cmd)
        assert r.returncode == 2
        line = _one_line(r)
        assert f"ROS_DOMAIN_ID={_domain()} is in use by /harden_probe" in line, line


@pytest.mark.parametrize(
    "cmd",
    [
        ["topic", "list"],
        ["param", "get", "/plant", "seed"],
        ["launch", "sim_lockstep"],
        ["run", "paper_2pct_150load"],
    ],
)
def test_security_enforced_without_a_keystore_is_one_line(cmd, tmp_path):
    env = {
        "ROS_SECURITY_ENABLE": "true",
        "ROS_SECURITY_STRATEGY": "Enforce",
        "ROS_SECURITY_KEYSTORE": "",
    }
    if cmd[0] == "run":
        cmd = [*cmd, "--out", str(tmp_path / "out"), "--bag", str(tmp_path / "bag")]
    r = fluxdrive(*cmd, env_extra=env)
    assert r.returncode == 2
    line = _one_line(r)
    assert "ROS_SECURITY_KEYSTORE is not set" in line and "Enforce" in line, line
    assert not (tmp_path / "bag").exists()


# an option ranged by a schema field (fluxdrive.core.schema.option): outside its range, one
# line naming the option and the range, exit 2, before anything starts
OUT_OF_RANGE = [
    (["benchmark", "paced", "--rate", "0"], "--rate", "[0.001, 10.0]"),
    (["benchmark", "paced", "--watchdog-s", "1e9"], "--watchdog-s", "[0.001, 3600.0]"),
    (["tune", "--rate", "11"], "--rate", "[0.001, 10.0]"),
    (["compare", "emf", "--settle-s", "-1"], "--settle-s", "[0.0, 60.0]"),
    (["compare", "emf", "--window-s", "nan"], "--window-s", "[0.05, 60.0]"),
    (["identify", "--max-current-pu", "0.9"], "--max-current-pu", "[1.0, 3.0]"),
    (["identify", "--max-voltage-pu", "1.5"], "--max-voltage-pu", "[0.02, 1.0]"),
    (["identify", "--seed", "-1"], "--seed", "[0, 4294967295]"),
    # options many commands share, each ranged by one field: --domain-id by the graph file's
    # domain_id (a DDS error and exit 0 before), the servers' --port (an OverflowError
    # traceback before), the CAN link's --decimation (a traceback on 0 or 300 before)
    (["topic", "list", "--domain-id", "500"], "--domain-id", "[0, 232]"),
    (["launch", "sim_lockstep", "--domain-id", "233"], "--domain-id", "[0, 232]"),
    (["scope", "--port", "70000"], "--port", "[0, 65535]"),
    (["foxglove", "--port", "70000"], "--port", "[0, 65535]"),
    (["run", "paper_2pct_150load", "--scope-port", "-1"], "--scope-port", "[0, 65535]"),
    (["can-emulator", "--decimation", "0"], "--decimation", "[1, 255]"),
    (["can-emulator", "--decimation", "300"], "--decimation", "[1, 255]"),
    (["bench", "--sil", "--decimation", "0"], "--decimation", "[1, 255]"),
    (["benchmark", "bench", "--decimation", "300"], "--decimation", "[1, 255]"),
    (["can-import", "x.log", "--out", "no_bag", "--decimation", "0"], "--decimation", "[1, 255]"),
]


@pytest.mark.parametrize(
    ("cmd", "flag", "rng"), OUT_OF_RANGE, ids=[" ".join(c[0]) for c in OUT_OF_RANGE]
)
def test_an_option_out_of_its_schema_range_is_one_line(cmd, flag, rng):
    r = fluxdrive(*cmd)
    line = _one_line(r)
    assert r.returncode == 2, (r.returncode, line)
    assert f"{flag} must be " in line and rng in line, line
