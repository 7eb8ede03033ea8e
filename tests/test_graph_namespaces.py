"""Two drives in two namespaces on one ROS domain (`run --namespace /a` and `/b`): every
topic of a drive is relative to its namespace, so neither hears the other at all -- even
with the same graph key (the same graph_id on every message, which takes the identity check
out of the picture) -- and each bag equals its solo run: the in-process run of the same
scenario, every frame, truth, estimate and controller output (the lockstep graph is equal
to it bit for bit, tests/test_graph_lockstep.py).  The two drives run different noise
seeds, so a sample of the other one in a bag would not go unnoticed.  Each bag also holds
/diagnostics and /rosout of its own drive only, stamped on the drive's sim time (the nodes
run with use_sim_time on the drive's /clock)."""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
DURATION_S = 0.3
_SHARED = ("/diagnostics", "/rosout")


def _scenario(seed: int) -> Path:
    from fluxdrive.drive.scenario import load_scenario, save_scenario

    src = ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml"
    out = Path(tempfile.mkdtemp(prefix="fluxdrive-ns-")) / f"seed{seed}.yaml"
    return save_scenario(load_scenario(src, overrides={"bench": {}, "seed": seed}), out)


def _reference(path: Path):
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive_bringup.launch.runs import shorten

    sc = load_scenario(path)
    shorten(sc, DURATION_S)
    return run_scenario(sc, progress=False)


def test_two_namespaced_drives_on_one_domain_each_record_their_solo_run(tmp_path):
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.drive.scenario import load_scenario
    from fluxdrive.io.bagio import read_run_bag
    from fluxdrive_bringup.launch.runs import result_from_bag
    from rosbags.highlevel import AnyReader

    dom = domain(47)
    # one graph key for both: the same graph_id, so only the namespaces keep them apart
    env = dict(os.environ, FLUXDRIVE_GRAPH_KEY="one-key-for-both-drives")
    runs = {"a": _scenario(11), "b": _scenario(22)}
    procs = {}
    for ns, sp in runs.items():
        cmd = [
            str(ROOT / "fluxdrive"),
            "run",
            str(sp),
            "--namespace",
            f"/{ns}",
            "--duration",
            str(DURATION_S),
            "--domain-id",
            str(dom),
            "--shared-domain",
            "--no-plots",
            "--timeout",
            "150",
            "--out",
            str(tmp_path / f"out_{ns}"),
            "--bag",
            str(tmp_path / f"bag_{ns}"),
        ]
        procs[ns] = subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
    logs = {ns: p.communicate(timeout=240)[0] for ns, p in procs.items()}
    for ns, p in procs.items():
        bag = tmp_path / f"bag_{ns}"
        assert bag.exists(), logs[ns][-3000:]
        rb = read_run_bag(bag)
        assert not [pr for pr in rb.problems if "another graph" in pr or "duplicate" in pr]
        assert np.array_equal(rb.frames[:, FR_SEQ], np.arange(len(rb.frames)))
        # the bag names the topics as a root-namespace drive's bag does
        with AnyReader([bag]) as r:
            names = {c.topic for c in r.connections}
            shared = {}
            for c, _, raw in r.messages([c for c in r.connections if c.topic in _SHARED]):
                shared.setdefault(c.topic, []).append(r.deserialize(raw, c.msgtype))
        assert {"/drive/frame", "/drive/duty", "/clock", "/obs/flux_measured/estimate"} <= names
        assert not any(t.startswith(f"/{ns}/") for t in names), names
        res, arr = result_from_bag(bag, load_scenario(runs[ns]), DURATION_S)
        ref = _reference(runs[ns])
        assert arr["n"] == ref.frames.shape[0] == int(round(DURATION_S * 1e4))
        assert all(v == 0 for v in arr["missing"].values()), (ns, arr["missing"])
        for field in ("frames", "truth", "est", "ctrl"):
            a, b = getattr(res, field), getattr(ref, field)
            assert np.array_equal(a, b), (ns, field, np.argwhere(a != b)[:5])
        assert p.returncode in (0, 1), (ns, logs[ns][-3000:])  # 1: report verdict
        assert "the graph failed" not in logs[ns] and "Traceback" not in logs[ns]
        # the nodes live in the namespace (their loggers say so) and heard nothing foreign
        assert f"[{ns}.plant]" in logs[ns] and f"[{ns}.obs.flux_measured]" in logs[ns]
        assert "message from another graph" not in logs[ns]
        assert "/clock 300" in logs[ns], logs[ns][-2000:]  # its own clock only
        # /diagnostics and /rosout: this drive's nodes only, on sim time (not the epoch)
        diag, log = shared.get("/diagnostics", []), shared.get("/rosout", [])
        assert diag and log, sorted(shared)
        assert all(s.name.startswith(f"/{ns}/") for d in diag for s in d.status)
        assert all(m.name.startswith(f"{ns}.") for m in log), {m.name for m in log}
        stamps = [d.header.stamp.sec + 1e-9 * d.header.stamp.nanosec for d in diag]
        assert max(stamps) <= DURATION_S + 1e-9, stamps
