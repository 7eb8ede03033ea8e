"""Errors of any node reach the console, not only its log: the launcher's death line of a
process carries the process's last error line, and a command's closing line (bench --sil's
"the bench failed") names it."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_a_dying_node_says_why_on_the_console():
    """The launcher's death line carries the process's last error line (a real controller
    node refusing host mode at D = 4: its 1000 Hz current loop above the 625 Hz a quarter of
    the 2.5 kHz sample rate allows), and failure_text() gives it for a command's closing
    line -- the console, not only the node's log."""
    pytest.importorskip("rclpy")
    from fluxdrive_bringup.launch.launcher import Graph, Launcher, NodeSpec
    from ros_domains import domain

    ctrl = NodeSpec(
        name="controller",
        node="controller",
        params=[str(REPO / "config" / "ros" / "controller.yaml")],
        parameters={"control_mode": "host", "decimation": 4},
    )
    idle = NodeSpec(name="idle", cmd=[sys.executable, "-c", "import time; time.sleep(60)"])
    out = io.StringIO()
    g = Graph("refusal", [ctrl, idle], domain_id=domain(56))
    launcher = Launcher(g, out=out, quiet=True, progress=False)
    code = launcher.run(120.0)
    death = [ln for ln in out.getvalue().splitlines() if "died" in ln]
    assert code == 1 and len(death) == 1, out.getvalue()
    assert "process 'controller' died (exit code 2" in death[0]
    assert "its last error: cannot start node 'controller'" in death[0]
    assert "current_bandwidth_hz" in death[0] and "625" in death[0]
    assert launcher.failure_text().startswith("; 'controller': cannot start node 'controller'")
