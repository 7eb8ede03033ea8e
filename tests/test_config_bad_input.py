"""Bad configuration on the ROS side answered in one line: a typo'd parameter name in a
ros__parameters file is refused with the file and key (rcl would silently ignore it),
YAML numbers with exponents (`1e-6`, `1.2e3`) are numbers in every file the project reads,
and a protection trip of the controller node (a NaN sample) is written to its log with the
values that tripped it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_ros")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")


def _env() -> dict[str, str]:
    return dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain(51)),
    )


def test_unknown_name_in_a_params_file_is_refused_with_file_and_key(tmp_path):
    f = tmp_path / "controller.yaml"
    f.write_text("/controller:\n  ros__parameters:\n    speed_bandwith_hz: 5.0\n")
    spec = {
        "process": "p",
        "nodes": [
            {
                "class": "controller",
                "name": "controller",
                "parameters": {"scenario": SCENARIO},
                "params_files": [str(f)],
            }
        ],
    }
    r = subprocess.run(
        [sys.executable, "-m", "fluxdrive_ros.runner", "--spec-json", json.dumps(spec)],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    err = r.stderr.strip()
    print(err)
    assert r.returncode == 2 and "Traceback" not in err
    line = err.splitlines()[-1]
    assert str(f) in line and "/controller.ros__parameters.speed_bandwith_hz" in line
    assert "did you mean 'speed_bandwidth_hz'" in line


def test_exponent_numbers_in_a_params_file(tmp_path):
    f = tmp_path / "controller.yaml"
    f.write_text(
        "/controller:\n  ros__parameters:\n    deadtime_comp_s: 1e-6\n"
        "    current_bandwidth_hz: 1.2e3\n"
    )
    code = (
        "import json, rclpy\nfrom fluxdrive_ros.runner import build_node\nrclpy.init()\n"
        f"n = build_node({{'class': 'controller', 'name': 'controller', 'parameters': "
        f"{{'scenario': {SCENARIO!r}}}, 'params_files': [{str(f)!r}]}})\n"
        "print(json.dumps([n.get_parameter(k).value for k in "
        "('deadtime_comp_s', 'current_bandwidth_hz', 'vdc_max_v')]))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    td, bw, vmax = json.loads(r.stdout.strip().splitlines()[-1])
    assert td == 1e-6 and bw == 1200.0
    assert vmax == pytest.approx(1.32 * 72.0)  # the bus window derived from the card


def test_nan_sample_trip_is_logged_with_its_values(capfd):
    from fluxdrive.drive.control import CS_FAULT, FAULT_BAD_SAMPLE
    from fluxdrive.drive.plant import FR_IB, FR_N, FR_SEQ, FR_VDC
    from foc_controller_node.node import ControllerNode
    from rclpy.parameter import Parameter

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain(52))
    try:
        node = ControllerNode(
            "controller", context=ctx, parameter_overrides=[Parameter("scenario", value=SCENARIO)]
        )
        try:
            fr = np.zeros(FR_N)
            fr[FR_VDC] = 72.0
            fr[FR_IB] = float("nan")
            fr[FR_SEQ] = 0.0
            node.seq.sensorless = False  # answer without waiting for an estimate
            node.seq.on_frame(0, fr)
            assert int(node.seq.cs[CS_FAULT]) == FAULT_BAD_SAMPLE
            assert "i_b = nan" in node.seq.fault_detail
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    err = capfd.readouterr().err
    line = next(ln for ln in err.splitlines() if "bad sample" in ln)
    print(line)
    assert "bad sample (NaN/inf): i_b = nan (frame 0); PWM off" in line
