"""A parameter set from the command line (`./fluxdrive param set`, a separate process, like
any foreign client) during a recorded run is in the bag as a /drive/param_marker published
by the node that took it, at the sample it took effect; replaying the bag with the recorded
settings (`@recorded`) applies the marker there and reproduces the recorded estimates
exactly (max |replayed - recorded| = 0), while the same replay without the marker does not."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml"
DURATION = 1.5  # simulated [s]; paced at RATE: ~6 s of wall time
RATE = 0.25


def test_cli_parameter_change_is_marked_and_replays_exactly(tmp_path):
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.io.bagio import read_run_bag
    from fluxdrive.replay.lab import expand_variants, replay_bag
    from fluxdrive_bringup.launch.launcher import Launcher
    from fluxdrive_bringup.launch.runs import graph_for_scenario, shorten

    dom = domain(54)
    sc = load_scenario(SCENARIO)
    shorten(sc, DURATION)
    # the driving observer and one shadow keep the graph light
    sc.observers = {k: sc.observers[k] for k in ("flux_measured", "emf_measured")}
    bag = tmp_path / "bag"
    g = graph_for_scenario(
        SCENARIO,
        sc,
        bag,
        "composed",
        DURATION,
        dom,
        extra={"plant": {"mode": "paced", "rate_factor": RATE}},
    )
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp_path / "logs")
    codes: list[int] = []
    th = threading.Thread(target=lambda: codes.append(launcher.run(timeout=180)), daemon=True)
    th.start()
    try:
        t_end = time.monotonic() + 90
        while (
            launcher.progress is None or launcher.progress[0] < 1000
        ) and time.monotonic() < t_end:
            time.sleep(0.02)
        assert launcher.progress is not None, "the graph did not start"
        env = dict(os.environ, ROS_DOMAIN_ID=str(dom), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        env.pop("FLUXDRIVE_GRAPH_KEY", None)  # a client outside the launch
        r = subprocess.run(
            [str(ROOT / "fluxdrive"), "param", "set", "/obs/flux_measured", "cutoff_hz", "40.0"],
            env={**env, "FLUXDRIVE_SKIP_BOOTSTRAP": "1"},
            capture_output=True,
            text=True,
            timeout=60,
            cwd=str(ROOT),
        )
        print(r.stdout.strip(), r.stderr.strip()[-300:])
        assert r.returncode == 0, r.stderr
        at = launcher.progress[0] if launcher.progress else None
    finally:
        th.join(timeout=180)
    assert codes == [0], tmp_path / "logs"
    n = int(round(DURATION * 1e4))

    rb = read_run_bag(bag)
    marks = [m for m in rb.markers if m["name"] == "cutoff_hz"]
    assert len(marks) == 1, rb.markers
    m = marks[0]
    print(f"marker {m} (the plant was at frame {at} when the CLI returned)")
    assert m["node"] == "/obs/flux_measured" and m["source"] == "node" and m["successful"]
    assert m["value"] == "40.0"
    assert 1000 <= m["seq"] < n, "the change came during the run"
    # the node's own log names the same sample
    log = (tmp_path / "logs" / "drive.log").read_text()
    assert f"{{'cutoff_hz': 40.0}}: applied from frame {m['seq']}" in log

    variants = expand_variants(["@recorded"], rb)
    res = replay_bag(rb, variants)
    print({k: f"{v:.3g}" for k, v in res.recorded_diff.items()})
    assert res.recorded_diff["flux_measured"] == 0.0
    assert res.recorded_diff["emf_measured"] == 0.0
    # up to the marker the estimates are those of the unchanged observer, after it not
    rb.markers = []
    plain = replay_bag(rb, variants)
    i = plain.names.index("flux_measured")
    k = int(np.searchsorted(rb.frames[:, FR_SEQ], m["seq"]))
    assert np.array_equal(plain.est[i, :k], res.est[i, :k])
    assert plain.recorded_diff["flux_measured"] > 1e-3
