"""Fault latching at the graph level: a latched controller fault is cleared only by an
explicit reset -- the controller's ~/reset_fault service, called by `./fluxdrive fault
reset` (node /fluxdrive_operator) -- and only while no node outside `allowed_operators`
holds a client of it.  After the reset the drive starts again from align (PWM on).  The
latch and the reset are each one DriveFault event on /drive/fault."""

from __future__ import annotations

import time

import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_ros")

from test_graph_bad_input import (  # noqa: E402,F401 - fixtures and helpers shared
    _controller,
    _est_bytes,
    frame_bytes,
    graph,
    run,
    wait_for,
    wait_matched,
)


def test_latched_fault_cleared_only_by_an_allowed_reset(graph, run, capsys):  # noqa: F811
    from fluxdrive_bringup.inspect.commands import main_fault
    from fluxdrive_ros.wire import EstimateWire, FrameWire

    from flux_drive_msgs.msg import (
        ControllerState,
        DriveFault,
        DutyCommand,
        PhaseFrame,
        RotorEstimate,
    )
    from flux_drive_msgs.srv import ResetFault
    from fluxdrive_ros import access

    sc, r = run
    ctl = _controller(graph, sc, position_wall_timeout_s=0.3)
    duties = graph.listen(DutyCommand, "/drive/duty")
    states = graph.listen(ControllerState, "/drive/controller_state")
    faults = graph.listen(DriveFault, "/drive/fault")
    fpub = graph.publisher(PhaseFrame, "/drive/frame")
    epub = graph.publisher(RotorEstimate, "/probe/estimate")
    wait_matched(fpub)
    wait_matched(epub)
    fw, ew = FrameWire(), EstimateWire("probe")
    for k in range(10):
        fpub.publish(frame_bytes(fw, r.frames[k], k))
        epub.publish(_est_bytes(ew, k))
    fpub.publish(frame_bytes(fw, r.frames[10], 10))  # its estimate never comes: trip
    wait_for(lambda: len(states) >= 11, what="the stale-input trip")
    assert states[10].fault_code == 8 and not duties[10].enable
    assert states[10].fault_reason == "stale input"
    wait_for(lambda: len(faults) >= 1, what="the DriveFault event")
    f = faults[0]
    assert (f.code, f.latched, f.source) == (DriveFault.STALE_INPUT, True, "/controller")
    assert "stale input at sample 10" in f.reason
    assert (f.header.stamp.sec, f.header.stamp.nanosec) == (0, 1_000_000)  # t_10 = 10 Ts

    # frames keep coming, estimates too: still latched (PWM off)
    for k in range(11, 20):
        fpub.publish(frame_bytes(fw, r.frames[k], k))
        epub.publish(_est_bytes(ew, k, True))
    wait_for(lambda: len(duties) >= 20, what="duties while latched")
    assert not any(d.enable for d in duties[10:20])

    dom = graph.ctx.get_domain_id()
    # a node outside allowed_operators holding a client of the service: refused
    rogue = rclpy.create_node("rogue", context=graph.ctx)
    rogue.create_client(ResetFault, "/controller/reset_fault")
    graph.ex.add_node(rogue)
    wait_for(
        lambda: "/rogue" in access.service_clients(ctl, "/controller/reset_fault"),
        what="the controller to see the rogue's client",
    )
    code = main_fault(["reset", "--domain-id", str(dom), "--wait", "10"])
    out = capsys.readouterr().out
    print(out)
    assert code == 1 and "REFUSED" in out and "/rogue" in out
    graph.ex.remove_node(rogue)
    rogue.destroy_node()

    # the operator alone: cleared, with the reason it cleared
    t_end = time.monotonic() + 15.0
    while True:
        code = main_fault(["reset", "--domain-id", str(dom), "--wait", "10"])
        out = capsys.readouterr().out
        if code == 0 or time.monotonic() > t_end:  # discovery may still show /rogue
            break
        time.sleep(0.5)
    print(out)
    assert code == 0 and "cleared latched fault 'stale input'" in out

    # the drive starts again: align, PWM on, no fault
    for k in range(20, 40):
        fpub.publish(frame_bytes(fw, r.frames[k], k))
        epub.publish(_est_bytes(ew, k, True))
    wait_for(lambda: len(states) >= 40, what="states after the reset")
    assert all(d.enable for d in duties[21:40])
    assert states[39].fault_reason == "" and states[39].mode != 4
    # one event for the latch, one for the reset; nothing while latched
    assert len(faults) == 2, [(f.code, f.reason) for f in faults]
    assert faults[1].code == DriveFault.FAULT_NONE and not faults[1].latched
    assert "'stale input' cleared" in faults[1].reason
