"""Access: the drive obeys commands only from the graph's own nodes
(allow-list by node name, commands marked with the launch's key -- fluxdrive_ros.access);
discovery stays on this machine unless the graph file opts in; ROS 2 security (SROS2) with
the installed middleware: what a user sees."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_ros")

from test_graph_bad_input import Graph, diag_status, values, wait_for  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DUTY = "/drive/duty"


@pytest.fixture
def graph():
    g = Graph(domain_id=domain(32))
    yield g
    g.close()


def test_plant_obeys_duty_commands_only_from_allowed_commanders(graph, tmp_path):
    """The probe (allowed) answers every frame with PWM on; before it, a rogue node sends
    PWM off for the same sample three ways -- marked as itself, unmarked, and claiming to be
    the probe with another launch's key.  Every frame shows the PWM on; every rogue command
    is counted on /diagnostics by reason."""
    from diagnostic_msgs.msg import DiagnosticArray
    from helpers_engine import make_scenario
    from spm_plant_sim.node import PlantNode

    from flux_drive_msgs.msg import DutyCommand, PhaseFrame
    from fluxdrive_ros import access, qos

    sc = make_scenario(
        tmp_path,
        name="acc",
        duration_s=0.01,
        speed_rpm=0.0,
        observers={"flux": {"variant": "paper"}},
    )
    rogue = rclpy.create_node("rogue", context=graph.ctx)
    graph.ex.add_node(rogue)
    graph.nodes.append(rogue)
    rpub = rogue.create_publisher(DutyCommand, DUTY, qos.SAMPLES)
    ppub = graph.publisher(DutyCommand, DUTY)
    diags = graph.listen(DiagnosticArray, "/diagnostics")
    frames: list = []
    marks = {
        "rogue": access.mark("/rogue", DUTY),
        "unmarked": "",
        "forged": access.mark("/probe", DUTY, key=b"another launch"),
    }

    def on_frame(m):
        frames.append(m)
        for fid in marks.values():
            d = DutyCommand(seq=m.seq, duty=[0.5, 0.5, 0.5], enable=False)
            d.commander = fid
            rpub.publish(d)
        d = DutyCommand(seq=m.seq, duty=[0.55, 0.5, 0.45], enable=True)
        d.commander = access.mark("/probe", DUTY)
        ppub.publish(d)

    graph.probe.create_subscription(PhaseFrame, "/drive/frame", on_frame, qos.reader("volatile"))
    graph.add(
        PlantNode,
        "plant",
        scenario=str(sc.source),
        diagnostics_period_s=0.2,
        exit_on_done=False,
        start_delay_s=0.5,
        allowed_commanders=["/probe"],
    )
    wait_for(lambda: len(frames) >= 100, what="100 frames")
    assert all(m.pwm_enabled for m in frames[2:100]), [m.seq for m in frames if not m.pwm_enabled]
    mark = len(diags)
    wait_for(lambda: diag_status(diags, "/plant: commands", mark) is not None, what="diagnostics")
    st = diag_status(diags, "/plant: commands")
    v = values(st)
    print("plant diagnostics:", v)
    n_answered = int(v["commands_accepted"])
    assert n_answered >= 98
    for reason in ("not_allowed", "unmarked", "bad_mark"):
        assert int(v[f"rejected_{reason}"]) >= n_answered, reason
    levels = {s.level for a in diags for s in a.status if s.name == "/plant: commands"}
    assert bytes([1]) in levels


def test_bridge_arms_and_resets_only_for_allowed_nodes(graph):
    """bench bridge (virtual CAN bus, the C drive answering it between periods, as before
    its first: arming writes and reads back the drive's parameters): /drive/arm and
    /drive/reset_fault obey only while every client of them is an allowed node; a disarm
    is always obeyed; duty commands from other nodes are dropped and counted."""
    import threading

    import can
    from bench_bridge.bridge_node import BenchBridgeNode
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.scenario import load_scenario, scenario_path
    from fluxdrive.drive.sim import DriveSetup
    from rclpy.parameter import Parameter

    from flux_drive_msgs.msg import DutyCommand
    from flux_drive_msgs.srv import Arm, ResetFault
    from fluxdrive_ros import access

    ch = new_virtual_channel()
    emu_bus = can.Bus(interface="virtual", channel=ch, fd=True)
    emu = DriveEmulator(DriveSetup(load_scenario(scenario_path("paper_2pct_150load"))), emu_bus)
    served = threading.Event()
    server = threading.Thread(target=emu.serve, args=(served,), daemon=True)
    server.start()
    bridge = BenchBridgeNode(
        context=graph.ctx,
        parameter_overrides=[
            Parameter("channel", value=ch),
            Parameter("stale_timeout_s", value=60.0),
        ],
    )
    graph.ex.add_node(bridge)
    try:
        ctl = rclpy.create_node("controller", context=graph.ctx)
        graph.ex.add_node(ctl)
        graph.nodes.append(ctl)
        arm_ctl = ctl.create_client(Arm, "/drive/arm")
        assert arm_ctl.wait_for_service(timeout_sec=10.0)

        def call(client, req, timeout=10.0):
            fut = client.call_async(req)
            wait_for(fut.done, timeout, "a service response")
            return fut.result()

        t_end = time.monotonic() + 60.0
        while True:  # until the bridge sees our client (discovery)
            res = call(arm_ctl, Arm.Request(arm=True))
            if res.success or "not known" not in res.message or time.monotonic() > t_end:
                break
            time.sleep(0.1)
        print("arm from /controller:", res.success, res.message)
        assert res.success and bridge.bridge.armed
        rogue = rclpy.create_node("rogue", context=graph.ctx)
        graph.ex.add_node(rogue)
        graph.nodes.append(rogue)
        arm_rogue = rogue.create_client(Arm, "/drive/arm")
        reset_rogue = rogue.create_client(ResetFault, "/drive/reset_fault")
        assert arm_rogue.wait_for_service(timeout_sec=10.0)
        res = call(arm_rogue, Arm.Request(arm=False))
        print("disarm from /rogue:", res.success, res.message)
        assert res.success and not bridge.bridge.armed  # stopping is never refused
        wait_for(
            lambda: "/rogue" in access.service_clients(bridge, "/drive/arm"),
            10.0,
            "discovery of the rogue client",
        )
        res = call(arm_rogue, Arm.Request(arm=True))
        print("arm from /rogue:", res.message)
        assert not res.success and "/rogue" in res.message and not bridge.bridge.armed
        res = call(arm_ctl, Arm.Request(arm=True))  # ambiguous while /rogue has a client
        assert not res.success and not bridge.bridge.armed
        res = call(reset_rogue, ResetFault.Request())
        print("reset from /rogue:", res.message)
        assert not res.success and "/rogue" in res.message
        # duties: the rogue's (unmarked / its own mark) are dropped, the controller's obeyed
        rp = rogue.create_publisher(DutyCommand, DUTY, 10)
        cp = ctl.create_publisher(DutyCommand, DUTY, 10)
        wait_for(
            lambda: rp.get_subscription_count() and cp.get_subscription_count(),
            10.0,
            "duty subscription",
        )
        # and the bridge's reader has matched both writers (else the first duties are lost)
        duty_sub = next(s for s in bridge.subscriptions if s.topic_name == DUTY)
        wait_for(lambda: duty_sub.get_publisher_count() >= 2, 10.0, "the bridge's duty reader")
        tx0 = bridge.bridge.counters["duty_tx"]
        for k in range(5):
            d = DutyCommand(seq=k, duty=[0.5, 0.5, 0.5], enable=True)
            rp.publish(d)
            d.commander = access.mark("/rogue", DUTY)
            rp.publish(d)
            d.commander = access.mark("/controller", DUTY)
            d.duty = [1.5, 0.5, 0.5]  # out of range: clamped and counted
            cp.publish(d)
        wait_for(
            lambda: bridge.guard.accepted >= 5 and bridge.guard.n_rejected >= 10,
            10.0,
            "the bridge to take the duties",
        )
        print("bridge guard:", bridge.guard.values(), "out of range:", bridge.duty_out_of_range)
        assert bridge.guard.accepted == 5 and bridge.guard.n_rejected == 10
        assert bridge.duty_out_of_range == 5
        assert bridge.bridge.counters["duty_tx"] - tx0 == 5  # only the controller's went out
    finally:
        graph.ex.remove_node(bridge)
        bridge.destroy_node()
        served.set()
        server.join(5.0)
        emu_bus.shutdown()


def test_launcher_keeps_discovery_local_and_keys_each_launch(monkeypatch):
    from fluxdrive_bringup.launch.launcher import Launcher, launcher_env_discovery, parse_graph

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")  # e.g. from a shell profile
    monkeypatch.delenv("FLUXDRIVE_GRAPH_KEY", raising=False)
    raw = {"name": "g", "nodes": [{"name": "x", "cmd": ["true"]}]}
    g = parse_graph(raw)
    la, lb = Launcher(g), Launcher(g)
    ea = la.env()
    assert ea["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    print("start line:", launcher_env_discovery(g))
    assert "ignored" in launcher_env_discovery(g)
    key = ea["FLUXDRIVE_GRAPH_KEY"]
    assert re.fullmatch(r"[0-9a-f]{32}", key)
    assert la.env()["FLUXDRIVE_GRAPH_KEY"] == key  # the same for restarted processes
    assert lb.env()["FLUXDRIVE_GRAPH_KEY"] != key  # a new one per launch
    opened = parse_graph({**raw, "discovery_range": "subnet"})
    assert Launcher(opened).env()["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    monkeypatch.setenv("FLUXDRIVE_GRAPH_KEY", "shared-with-nodes-started-by-hand")
    assert Launcher(g).env()["FLUXDRIVE_GRAPH_KEY"] == "shared-with-nodes-started-by-hand"


def _start_plant(env_extra: dict[str, str]) -> subprocess.CompletedProcess:
    spec = {
        "process": "drive",
        "nodes": [
            {
                "class": "plant",
                "name": "plant",
                "parameters": {"scenario": str(ROOT / "config/scenarios/paper_2pct_150load.yaml")},
            }
        ],
    }
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain(34)),
        **env_extra,
    )
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive_ros.runner", "--spec-json", json.dumps(spec)],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=str(ROOT),
    )


def test_security_enforced_without_a_keystore_refuses_to_start(tmp_path):
    r = _start_plant(
        {
            "ROS_SECURITY_ENABLE": "true",
            "ROS_SECURITY_STRATEGY": "Enforce",
            "ROS_SECURITY_KEYSTORE": str(tmp_path / "no_keystore"),
        }
    )
    out = (r.stdout + r.stderr).strip()
    print(out.splitlines()[-1])
    assert r.returncode == 2 and "Traceback" not in out
    assert "cannot start process 'drive': ROS 2 security is on" in out
    assert "no_keystore/enclaves' does not exist" in out


def test_keystore_made_here_is_found_but_this_fast_dds_has_no_security(tmp_path):
    """The openssl-made keystore is valid (certificates verify, rcl finds the enclave); the
    wheels' Fast DDS then refuses to create a secured participant: the node does not start
    (and never runs unsecured while security is asked for)."""
    from fluxdrive_ros.security import make_keystore

    ks = tmp_path / "keystore"
    (enc,) = make_keystore(ks, ["/fluxdrive"])
    names = sorted(p.name for p in enc.iterdir())
    assert names == [
        "cert.pem",
        "governance.p7s",
        "identity_ca.cert.pem",
        "key.pem",
        "permissions.p7s",
        "permissions.xml",
        "permissions_ca.cert.pem",
    ]
    v = subprocess.run(
        ["openssl", "verify", "-CAfile", str(ks / "public/ca.cert.pem"), str(enc / "cert.pem")],
        capture_output=True,
        text=True,
    )
    assert v.returncode == 0, v.stderr
    for strategy in ("Enforce", "Permissive"):
        r = _start_plant(
            {
                "ROS_SECURITY_ENABLE": "true",
                "ROS_SECURITY_STRATEGY": strategy,
                "ROS_SECURITY_KEYSTORE": str(ks),
                "ROS_SECURITY_ENCLAVE_OVERRIDE": "/fluxdrive",
            }
        )
        out = (r.stdout + r.stderr).strip()
        print(strategy, "->", out.splitlines()[-1])
        assert r.returncode == 2 and "Traceback" not in out
        assert "Found security directory" in out
        assert "built without DDS-Security" in out.splitlines()[-1]
