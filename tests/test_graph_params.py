"""Every declared parameter of every node (plant, observer, controller, recorder, bench
bridge) is documented (description, unit for numbers, range or choices) and refuses a wrong
type and an out-of-range value with a reason, leaving the value unchanged.
A bad value given at start-up (override, ros__parameters file) stops the node with a
one-line reason naming the parameter -- and the file."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_ros")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")
RCLPY_OWN = {"use_sim_time", "start_type_description_service"}  # declared by rclpy itself


@pytest.fixture(scope="module")
def ctx():
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    c = rclpy.Context()
    rclpy.init(context=c, domain_id=domain(21))
    yield c
    rclpy.shutdown(context=c)


def _make(kind: str, ctx, tmp: Path, **params):
    from rclpy.parameter import Parameter

    ov = [Parameter(k, value=v) for k, v in params.items()]
    if kind == "plant":
        from spm_plant_sim.node import PlantNode

        return PlantNode(
            "plant", context=ctx, parameter_overrides=[Parameter("scenario", value=SCENARIO), *ov]
        )
    if kind == "observer":
        from flux_observer_node.node import ObserverNode

        return ObserverNode(
            "flux_measured",
            namespace="/obs",
            context=ctx,
            parameter_overrides=[Parameter("scenario", value=SCENARIO), *ov],
        )
    if kind == "controller":
        from foc_controller_node.node import ControllerNode

        return ControllerNode(
            "controller",
            context=ctx,
            parameter_overrides=[Parameter("scenario", value=SCENARIO), *ov],
        )
    if kind == "recorder":
        from fluxdrive_bringup.record.recorder import RecorderNode

        return RecorderNode(
            "recorder",
            context=ctx,
            parameter_overrides=[
                Parameter("bag_dir", value=str(tmp / "bag")),
                Parameter("exit_on_done", value=False),
                *ov,
            ],
        )
    from bench_bridge.bridge_node import BenchBridgeNode
    from fluxdrive.can.loop import new_virtual_channel

    return BenchBridgeNode(
        context=ctx, parameter_overrides=[Parameter("channel", value=new_virtual_channel()), *ov]
    )


def _close(node) -> None:
    close = getattr(node, "close", None)
    if close is not None and not hasattr(node, "bridge"):
        close()
    node.destroy_node()


def _wrong_type_value(ptype):
    from rcl_interfaces.msg import ParameterType as T

    return {
        T.PARAMETER_DOUBLE: "fast",
        T.PARAMETER_INTEGER: "many",
        T.PARAMETER_BOOL: "yes",
        T.PARAMETER_STRING: 2.5,
        T.PARAMETER_STRING_ARRAY: 7.0,
    }[ptype]


def _outside(d) -> list:
    """Values beyond each end of the descriptor's range."""
    if d.floating_point_range:
        r = d.floating_point_range[0]
        span = max(abs(r.to_value), 1.0)
        return [r.to_value + span, r.from_value - span]
    if d.integer_range:
        r = d.integer_range[0]
        return [r.to_value + 1, r.from_value - 1]
    return []


@pytest.mark.parametrize("kind", ["plant", "observer", "controller", "recorder", "bridge"])
def test_every_parameter_is_documented_and_refuses_bad_values(kind, ctx, tmp_path):
    from rcl_interfaces.msg import ParameterType as T
    from rclpy.parameter import Parameter

    node = _make(kind, ctx, tmp_path)
    try:
        names = sorted(set(node._parameters) - RCLPY_OWN)
        assert len(names) >= 8
        checked = {"type": 0, "range": 0, "choice": 0, "read_only": 0}
        for name in names:
            d = node.describe_parameter(name)
            before = node.get_parameter(name).value
            numeric = d.type in (T.PARAMETER_DOUBLE, T.PARAMETER_INTEGER)
            assert d.description.strip(), f"{kind}.{name}: no description"
            if numeric:
                assert re.search(r"\[[^\]]+\]$", d.description), f"{kind}.{name}: no unit"
                assert d.floating_point_range or d.integer_range, f"{kind}.{name}: no range"
            tries = [_wrong_type_value(d.type)] + _outside(d)
            if d.additional_constraints.startswith("one of:"):
                tries.append("no-such-choice")
                checked["choice"] += 1
            for j, bad in enumerate(tries):
                res = node.set_parameters([Parameter(name, value=bad)])[0]
                assert not res.successful, f"{kind}.{name} = {bad!r} was accepted"
                assert res.reason.strip(), f"{kind}.{name} = {bad!r}: no reason"
                assert node.get_parameter(name).value == before
                checked["type" if j == 0 else "range"] += 1
            checked["read_only"] += int(d.read_only)
        print(f"{kind}: {len(names)} parameters, refused: {checked}")
        # a live one: an in-range value is taken, an out-of-range one says why
        live = [
            n
            for n in names
            if not node.describe_parameter(n).read_only and _outside(node.describe_parameter(n))
        ]
        if live:
            d = node.describe_parameter(live[0])
            res = node.set_parameters([Parameter(live[0], value=_outside(d)[0])])[0]
            print(f"  e.g. {live[0]} = {_outside(d)[0]}: {res.reason}")
    finally:
        _close(node)


@pytest.mark.parametrize(
    "kind, name, value, words",
    [
        ("plant", "duration_s", -1.0, ["duration_s", "range"]),
        ("plant", "seed", "one", ["seed", "type"]),
        ("controller", "position_timeout_s", 99.0, ["position_timeout_s", "range"]),
        ("observer", "variant", "magic", ["variant", "one of"]),
        ("bridge", "bitrate", 5, ["bitrate", "range"]),
    ],
)
def test_bad_start_values_stop_the_node_with_the_reason(ctx, tmp_path, kind, name, value, words):
    from rclpy.exceptions import ParameterException

    with pytest.raises((ValueError, ParameterException)) as ei:
        _close(_make(kind, ctx, tmp_path, **{name: value}))
    msg = str(ei.value)
    print(f"{kind} {name}={value!r}: {msg}")
    for w in words:
        assert w.lower() in msg.lower()


def _run_node(args: list[str], timeout: float = 60.0) -> subprocess.CompletedProcess:
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain(22)),
    )
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive_ros.runner", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=str(ROOT),
    )


@pytest.mark.parametrize(
    "yaml_text, words",
    [
        ("/plant:\n  ros__parameters:\n    duration_s: long\n", ["duration_s"]),
        ("/plant:\n  ros__parameters:\n    duration_s: 99999.0\n", ["duration_s", "range"]),
        ("/plant:\n  ros__parameters: [1, 2]\n", []),
        ("/plant:\n  ros__parameters:\n    duration_s: [1.0\n", []),
    ],
)
def test_a_bad_parameter_file_names_the_file_and_the_key(tmp_path, yaml_text, words):
    import json

    f = tmp_path / "plant_bad.yaml"
    f.write_text(yaml_text)
    spec = {
        "process": "p",
        "nodes": [
            {
                "class": "plant",
                "name": "plant",
                "parameters": {"scenario": SCENARIO},
                "params_files": [str(f)],
            }
        ],
    }
    r = _run_node(["--spec-json", json.dumps(spec)])
    out = (r.stdout + r.stderr).strip()
    print(out.splitlines()[-1] if out else "")
    assert r.returncode != 0
    assert "Traceback" not in out
    last = out.splitlines()[-1]
    assert str(f) in last, "the file is named"
    for w in words:
        assert w in last
