"""`./fluxdrive bench --pil`: the whole bench path with the board image that would be flashed
(firmware/board/nucleo_g474) on the virtual board (fluxdrive.can.vboard) as the drive, in
split mode at D = 4 on the ideal-bench 2 % case of test_bench_sil.py: every sample in the
bag, in order, and θ̃ RMS against the in-process split run of the same case."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("msgpack")  # python-can's udp_multicast needs it
# the drive paced against the graph over a CAN bus: wall-clock deadlines, so alone
pytestmark = pytest.mark.serial

from fluxdrive.analysis.metrics import compute  # noqa: E402
from fluxdrive.drive.scenario import load_scenario  # noqa: E402
from fluxdrive.drive.sim import run_scenario  # noqa: E402
from test_bench_sil import DURATION_S, D, _case  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def test_bench_pil_split_mode_records_every_sample_and_matches_in_process(tmp_path):
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive_bringup.measure.sil import result_from_sil_bag

    sp = _case(tmp_path / "pil_2pct_split.yaml")
    bag = tmp_path / "bag"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    p = subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "bench", "--pil", str(sp), "--mode", "split"]
        + ["--decimation", str(D), "--bag", str(bag), "--domain-id", str(domain(43)), "--quiet"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=480,
    )
    print(p.stdout[-3000:])
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert "board image on the virtual board" in p.stdout
    sc = load_scenario(sp)
    n = int(round(DURATION_S / sc.machine.ts_s)) // D
    res, arr = result_from_sil_bag(bag, sc, D, Path(str(bag) + "-report") / "truth.npy")
    assert arr["n"] == n
    for topic in ("frame", "estimate/flux_measured", "controller_state"):
        assert arr["missing"][topic] == 0, (topic, arr["missing"])
    assert np.array_equal(arr["frames"][:, FR_SEQ], np.arange(n))
    ref = compute(run_scenario(sc, progress=False))
    th_ref = ref["observers"]["flux_measured"]["theta_err_rms_deg"]
    th_pil = compute(res)["observers"]["flux_measured"]["theta_err_rms_deg"]
    print(f"theta~ RMS: PIL graph {th_pil:.3f} deg, in-process split {th_ref:.3f} deg")
    assert ref["stable"]
    # the SIL graph's bound (test_bench_sil.py) with the board's timer preload (one period
    # more between the duty computed and applied) and its 1 ms bootstrap charge
    assert abs(th_pil - th_ref) < 0.3


def test_bench_pil_refuses_a_decimation_without_an_image():
    p = subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "bench", "--pil", "--decimation", "2"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1].startswith("[bench] --pil: the board image is built")
