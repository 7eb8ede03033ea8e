"""A parameter marker marks a change: a set to the value in force -- what a client does when
it re-sends a request it saw no answer to (inspect.commands._call) -- is accepted and not
marked again, so the bag holds one marker per change."""

from __future__ import annotations

import time

import rclpy
from fluxdrive.io.topics import MARKER
from rclpy.parameter import Parameter
from ros_domains import domain

from flux_drive_msgs.msg import ParameterMarker
from fluxdrive_ros import params, qos


def test_a_repeated_set_is_accepted_and_marked_once():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain(73))
    node = rclpy.create_node("marker_once", context=ctx)
    try:
        node.declare_parameter("cutoff_hz", 20.0)
        applied: list[dict] = []
        params.on_set(
            node,
            [params.P("cutoff_hz", 20.0, "the low-pass's corner [Hz]", "Hz", 0.1, 1000.0)],
            lambda changes: applied.append(dict(changes)) or "applied",
            sample=lambda: 1000 + len(applied),
            ts_s=1e-4,
        )
        got: list[ParameterMarker] = []
        node.create_subscription(ParameterMarker, MARKER.lstrip("/"), got.append, qos.MARKERS)
        # a change, its re-sent copy, a second change, then a last change whose marker shows
        # the others are in: one publisher's reliable markers arrive in the order sent
        for value in (40.0, 40.0, 25.0, 30.0):
            (res,) = node.set_parameters([Parameter("cutoff_hz", value=value)])
            assert res.successful, res.reason
        t_end = time.monotonic() + 60.0
        ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        while not any(m.value == "30.0" for m in got) and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        assert [(m.name, m.value, m.successful) for m in got] == [
            ("cutoff_hz", "40.0", True),
            ("cutoff_hz", "25.0", True),
            ("cutoff_hz", "30.0", True),
        ]
        # every set reached the node's apply (the repeat changes nothing there either)
        assert [a["cutoff_hz"] for a in applied] == [40.0, 40.0, 25.0, 30.0]
        assert node.get_parameter("cutoff_hz").value == 30.0
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
