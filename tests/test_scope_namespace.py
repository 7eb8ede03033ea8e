"""The scope looks at a drive in a namespace: the tap of drive /bench_a publishes its
envelopes on /bench_a/scope/envelope, the scope server (`--namespace /bench_a`, as
`add_scope` starts it for a namespaced graph) reads them there and puts its refusal markers
on /bench_a/drive/param_marker -- where that drive's recorder and tap listen -- and nothing
on the root namespace's /drive/param_marker."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
NS = "/bench_a"


def _spin_until(ex, cond, timeout_s: float = 15.0) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if cond():
            return True
        ex.spin_once(timeout_sec=0.05)
    return cond()


def test_scope_in_a_namespace_taps_and_marks_its_own_drive():
    from fluxdrive_bringup.launch.launcher import Graph, NodeSpec, add_scope
    from fluxdrive_bringup.view.scope import RosSide
    from fluxdrive_bringup.view.scope_tap import ScopeTapNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    import flux_drive_msgs.msg as fm
    from fluxdrive_ros import qos

    g = Graph(name="ns", nodes=[NodeSpec(name="plant", node="plant")], namespace=NS)
    add_scope(g)
    server = next(n for n in g.nodes if n.name == "scope")
    assert server.cmd[-2:] == ["--namespace", NS]

    dom = domain(39)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=dom)
    ros = None
    try:
        sc = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")
        tap = ScopeTapNode(
            "scope_tap",
            namespace=NS,
            context=ctx,
            parameter_overrides=[Parameter("scenario", value=sc)],
        )
        assert tap.envelope_topic == f"{NS}/scope/envelope"
        listener = rclpy.create_node("listener", context=ctx)
        ours: list = []
        root: list = []
        listener.create_subscription(
            fm.ParameterMarker, f"{NS}/drive/param_marker", ours.append, qos.MARKERS
        )
        listener.create_subscription(
            fm.ParameterMarker, "/drive/param_marker", root.append, qos.MARKERS
        )
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(tap)
        ex.add_node(listener)
        ros = RosSide(dom, lambda text: None, attach_wait_s=60.0, quiet=True, namespace=NS)
        # the server reads the envelopes where this drive's tap writes them
        assert _spin_until(ex, lambda: ros.sub.get_publisher_count() >= 1)
        assert _spin_until(ex, lambda: ros.pub_marker.get_subscription_count() >= 1)
        ros.publish_marker(
            f"{NS}/controller", "current_bandwidth_hz", "9000.0", False, "refused: too high"
        )
        assert _spin_until(ex, lambda: len(ours) >= 1)
        ex.spin_once(timeout_sec=0.3)
    finally:
        if ros is not None:
            ros.close()
        ctx.try_shutdown()
    m = ours[0]
    assert (m.node, m.name, m.value, m.successful) == (
        f"{NS}/controller",
        "current_bandwidth_hz",
        "9000.0",
        False,
    )
    assert m.source == "scope" and m.reason == "refused: too high"
    assert root == []  # nothing on the root drive's marker topic
