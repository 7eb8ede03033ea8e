"""Bags record the QoS each topic's publishers really offer: /rosout as rcl offers it
(reliable, transient-local, kept 10 s) and /diagnostics as fluxdrive_ros.diagnostics does
(reliable, volatile), read back from live publishers on a real DDS domain."""

from __future__ import annotations

import time

import pytest
from fluxdrive.io.topics import DIAGNOSTICS, ROSOUT, offered_lifespan_s, offered_qos
from ros_domains import domain


@pytest.fixture
def ros_node(monkeypatch):
    import rclpy

    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain(59)))
    rclpy.init()
    node = rclpy.create_node("qos_probe_reader")
    yield node
    node.destroy_node()
    rclpy.shutdown()


def _offered(node, topic: str, deadline_s: float = 20.0):
    t_end = time.monotonic() + deadline_s
    while time.monotonic() < t_end:
        infos = [
            i for i in node.get_publishers_info_by_topic(topic) if i.node_name != node.get_name()
        ]
        if infos:
            return infos[0].qos_profile
        time.sleep(0.05)
    raise AssertionError(f"no publisher of {topic} discovered in {deadline_s} s")


def test_recorded_qos_is_what_the_publishers_offer(ros_node):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from fluxdrive_ros import diagnostics

    pub_node = rclpy.create_node("qos_probe_publisher")  # its rosout publisher comes with it
    try:
        pub_node.create_publisher(DiagnosticArray, DIAGNOSTICS, diagnostics.QOS)
        for topic in (ROSOUT, DIAGNOSTICS):
            q = _offered(ros_node, topic)
            depth, durability = offered_qos(topic)
            want = {
                "transient_local": DurabilityPolicy.TRANSIENT_LOCAL,
                "volatile": DurabilityPolicy.VOLATILE,
            }[durability]
            assert q.durability == want, topic
            assert q.reliability == ReliabilityPolicy.RELIABLE, topic
            life = offered_lifespan_s(topic)
            if life is not None:
                assert q.lifespan.nanoseconds == int(life * 1e9), topic
        assert diagnostics.QOS.depth == offered_qos(DIAGNOSTICS)[0]
    finally:
        pub_node.destroy_node()
