"""Bad input through the graph : NaN/inf/out-of-range frames and seq
repeats, reversals and jumps published onto running observer and controller nodes; a lost
or stale position source; malformed duty commands at the plant.  The nodes run in this
process on a SingleThreadedExecutor in a background thread (rclpy's multi-threaded executor
busy-waits here); a probe node plays the rest of the graph.  Checked: the estimate flags,
the counts and levels on /diagnostics, and PWM off (DutyCommand.enable = false, latched
"stale input" in ControllerState.fault_reason) when the position source goes stale."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_ros")

TS = 1e-4


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short closed-loop run whose frames are replayed onto the nodes."""
    from fluxdrive.drive.sim import run_scenario
    from helpers_engine import make_scenario

    tmp = tmp_path_factory.mktemp("badin")
    sc = make_scenario(
        tmp,
        name="badin",
        duration_s=0.6,
        speed_rpm=300.0,
        steady_window_s=[0.4, 0.6],
        observers={"flux": {"variant": "paper"}},
    )
    return sc, run_scenario(sc, progress=False)


class Graph:
    """rclpy context + executor thread + probe node; nodes added on the fly."""

    open: list[Graph] = []  # the graphs not closed yet (wait_matched looks at their readers)

    def __init__(self, domain_id: int):
        from fluxdrive_ros import intra

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ["FLUXDRIVE_INTRA_PROCESS"] = "0"  # every message over DDS, like separate
        intra._BUS = None
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.probe = rclpy.create_node("probe", context=self.ctx)
        self.ex.add_node(self.probe)
        self.nodes = [self.probe]
        self.thread = threading.Thread(target=self.ex.spin, daemon=True)
        self.thread.start()
        Graph.open.append(self)

    def add(self, cls, name: str, namespace: str = "", **params):
        from rclpy.parameter import Parameter

        node = cls(
            name,
            namespace=namespace,
            context=self.ctx,
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
        )
        self.ex.add_node(node)
        self.nodes.append(node)
        return node

    def listen(self, msg_cls, topic: str) -> list:
        from fluxdrive_ros import qos

        got: list = []
        self.probe.create_subscription(msg_cls, topic, got.append, qos.reader("volatile"))
        return got

    def publisher(self, msg_cls, topic: str):
        from fluxdrive_ros import qos

        return self.probe.create_publisher(msg_cls, topic, qos.SAMPLES)

    def close(self) -> None:
        Graph.open.remove(self)
        self.ex.shutdown()
        self.thread.join(timeout=5.0)
        for n in self.nodes:
            n.destroy_node()
        rclpy.shutdown(context=self.ctx)
        os.environ.pop("FLUXDRIVE_INTRA_PROCESS", None)


@pytest.fixture
def graph():
    g = Graph(domain_id=domain(24))
    yield g
    g.close()


def wait_for(cond, timeout: float = 20.0, what: str = "condition") -> None:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


def wait_matched(pub, n: int = 1) -> None:
    """Until `n` readers have matched the writer `pub` and every reader of its topic in the
    open test graphs has matched it back: a reliable reader drops what comes from a writer
    it has not matched yet, so the first messages would be lost."""
    wait_for(lambda: pub.get_subscription_count() >= n, 10.0, "discovery")
    readers = [
        s
        for g in Graph.open
        for nd in g.nodes
        for s in nd.subscriptions
        if s.topic_name == pub.topic_name
    ]
    wait_for(
        lambda: all(s.get_publisher_count() >= 1 for s in readers),
        10.0,
        f"the readers of {pub.topic_name} matching its writer",
    )


def diag_status(diags: list, name: str, after: int = 0):
    """Latest DiagnosticStatus called `name` among diags[after:], or None."""
    for arr in reversed(diags[after:]):
        for st in arr.status:
            if st.name == name:
                return st
    return None


def values(st) -> dict[str, str]:
    return {kv.key: kv.value for kv in st.values}


def frame_bytes(fw, fr: np.ndarray, seq: int) -> bytes:
    from fluxdrive.drive.plant import FR_SEQ

    fr = fr.copy()
    fr[FR_SEQ] = seq
    ns = seq * 100_000
    return fw.pack(fr, ns // 1_000_000_000, ns % 1_000_000_000)


def test_observer_flags_holds_and_reports_bad_frames(graph, run):
    """NaN, +inf, -inf and a 10x-full-scale current, then a repeat, a backwards frame and a
    10-frame gap: each estimate flagged invalid and finite, the angle held, the counts on
    /diagnostics; good frames afterwards give valid estimates again."""
    from diagnostic_msgs.msg import DiagnosticArray
    from flux_observer_node.node import ObserverNode
    from fluxdrive.drive.plant import FR_IA, FR_IB, FR_VAB, FR_VDC
    from fluxdrive_ros.wire import FrameWire

    from flux_drive_msgs.msg import PhaseFrame, RotorEstimate

    sc, r = run
    graph.add(ObserverNode, "flux", "/obs", scenario=str(sc.source), diagnostics_period_s=0.2)
    ests = graph.listen(RotorEstimate, "/obs/flux/estimate")
    diags = graph.listen(DiagnosticArray, "/diagnostics")
    pub = graph.publisher(PhaseFrame, "/drive/frame")
    wait_matched(pub)
    fw = FrameWire()
    frames = r.frames
    k0, n_good = 2000, 2500  # from 0.2 s: converged well before the faults
    for k in range(k0, k0 + n_good):
        pub.publish(frame_bytes(fw, frames[k], k))
    wait_for(lambda: len(ests) >= n_good, what="estimates of the good frames")
    assert ests[-1].valid, "the observer should have converged on 0.25 s of good frames"
    k = k0 + n_good
    bad = {
        k: (FR_IA, np.nan),
        k + 1: (FR_VDC, np.inf),
        k + 2: (FR_VAB, -np.inf),
        k + 3: (FR_IB, 10 * sc.machine.current_range_a),
    }
    # the four bad frames, a good one, its repeat, a backwards one, then k+5..k+14 lost
    seqs = [k, k + 1, k + 2, k + 3, k + 4, k + 4, k + 2]
    for i, s in enumerate(seqs):
        fr = frames[s].copy()
        if s in bad and seqs.index(s) == i:
            j, v = bad[s]
            fr[j] = v
        pub.publish(frame_bytes(fw, fr, s))
    seqs_after = list(range(k + 15, k + 1000))
    for s in seqs_after:
        pub.publish(frame_bytes(fw, frames[s], s))
    n_all = n_good + len(seqs) + len(seqs_after)
    wait_for(lambda: len(ests) >= n_all, what="all estimates")
    mark = len(diags)
    wait_for(
        lambda: diag_status(diags, "/obs/flux: input", mark) is not None,
        what="a diagnostics report",
    )
    flagged = ests[n_good : n_good + len(seqs) + 1]
    print(
        "estimates (seq, valid, theta_e):", [(e.seq, e.valid, round(e.theta_e, 4)) for e in flagged]
    )
    assert [e.seq for e in flagged] == [*seqs, k + 15]
    # bad ones, the first good one after them (it follows a gap), repeat, backwards, gap
    assert not any(e.valid for e in flagged)
    th = np.array([e.theta_e for e in ests])
    assert np.all(np.isfinite(th)) and np.all(np.isfinite([e.omega_e for e in ests]))
    # held: between consecutive bad estimates the angle only coasts (w^ Ts, < 0.1 rad)
    d = np.abs(np.angle(np.exp(1j * np.diff(th[n_good - 1 : n_good + 4]))))
    assert d.max() < 0.1, d
    assert ests[-1].valid, "valid again after good frames"
    st = diag_status(diags, "/obs/flux: input")
    v = values(st)
    print("diagnostics:", st.level, st.message, v)
    assert int(v["bad_samples"]) == 4 and int(v["out_of_range"]) == 1
    # missing = periods coasted across: the 4 bad ones (seen as a gap by the next good
    # frame, the engine's policy) + the 10 lost
    assert int(v["repeated_or_backwards"]) == 2 and int(v["missing"]) == 14
    assert int(v["frames"]) == n_all
    # the report that first counts the bad frames is not OK: WARN (bad input among good), or
    # ERROR when the report's period held only unusable frames (a loaded machine delivers
    # the frames in bursts, so a period may start and end inside the bad ones)
    first_bad = next(
        s
        for a in diags
        for s in a.status
        if s.name == "/obs/flux: input" and int(values(s)["bad_samples"]) > 0
    )
    assert first_bad.level in (bytes([1]), bytes([2])), (first_bad.level, first_bad.message)


def _controller(graph, sc, **params):
    from foc_controller_node.node import ControllerNode

    return graph.add(
        ControllerNode,
        "controller",
        scenario=str(sc.source),
        position_source="estimate",
        estimate_topic="/probe/estimate",
        diagnostics_period_s=0.2,
        **params,
    )


def _est_bytes(ew, seq: int, valid: bool = False) -> bytes:
    from fluxdrive.drive.observers import ES_N, ES_VALID

    es = np.zeros(ES_N)
    es[ES_VALID] = float(valid)
    ns = seq * 100_000
    return ew.pack(es, seq, ns // 1_000_000_000, ns % 1_000_000_000)


def test_controller_pwm_off_when_position_source_goes_stale(graph, run):
    """Frames keep coming (bench / paced plant) but the estimates stop: after
    position_timeout_s of sample time the duty goes out with enable = false and the state
    says "stale input", latched; the input counts (repeat, backwards, gap) on /diagnostics."""
    from diagnostic_msgs.msg import DiagnosticArray
    from fluxdrive_ros.wire import EstimateWire, FrameWire

    from flux_drive_msgs.msg import ControllerState, DutyCommand, PhaseFrame, RotorEstimate

    sc, r = run
    _controller(graph, sc, position_timeout_s=0.01)  # 100 periods
    duties = graph.listen(DutyCommand, "/drive/duty")
    states = graph.listen(ControllerState, "/drive/controller_state")
    diags = graph.listen(DiagnosticArray, "/diagnostics")
    fpub = graph.publisher(PhaseFrame, "/drive/frame")
    epub = graph.publisher(RotorEstimate, "/probe/estimate")
    wait_matched(fpub)
    wait_matched(epub)
    fw, ew = FrameWire(), EstimateWire("probe")
    for k in range(200):  # align phase: PWM on
        fpub.publish(frame_bytes(fw, r.frames[k], k))
        epub.publish(_est_bytes(ew, k))
    for k in (199, 150):  # a repeat and a backwards frame: dropped
        fpub.publish(frame_bytes(fw, r.frames[k], k))
    for k in range(205, 400):  # 200..204 lost upstream (a gap); no estimates any more
        fpub.publish(frame_bytes(fw, r.frames[k], k))
    wait_for(lambda: len(duties) >= 200 + 195 - 0, what="duties")
    wait_for(lambda: len(states) >= len(duties), what="controller states")
    seqs = [d.seq for d in duties]
    en = {d.seq: d.enable for d in duties}
    assert seqs == [*range(200), *range(205, 400)]  # in order, gap skipped, nothing twice
    assert all(en[k] for k in range(1, 200)), "PWM on in the align phase"
    # estimate 205 missing; frame 305 = 100 periods later trips: 205..400 all answered off
    assert not any(en[k] for k in range(205, 400))
    st = {s.seq: s for s in states}
    assert st[199].mode == 1 and st[199].fault_reason == ""
    assert st[399].mode == 4 and st[399].fault_code == 8
    assert st[399].fault_reason == "stale input"
    print(
        "first duty after the gap:",
        duties[200].seq,
        duties[200].enable,
        "state:",
        st[205].fault_reason,
    )
    mark = len(diags)
    wait_for(
        lambda: (
            diag_status(diags, "/controller: input", mark) is not None
            and diag_status(diags, "/controller: state", mark) is not None
        ),
        what="diagnostics",
    )
    s_in = diag_status(diags, "/controller: input")
    s_st = diag_status(diags, "/controller: state")
    print("diagnostics:", s_in.message, values(s_in), "|", s_st.level, s_st.message)
    vi = values(s_in)
    assert int(vi["repeated_or_backwards"]) == 2 and int(vi["missing_frames"]) == 5
    assert s_st.level == bytes([2]) and "stale input" in s_st.message
    assert "no position estimate for frame 205" in s_st.message
    assert values(s_st)["pwm_enabled"] == "False"
    # latched: estimates coming back change nothing
    for k in range(400, 450):
        epub.publish(_est_bytes(ew, k, True))
        fpub.publish(frame_bytes(fw, r.frames[k], k))
    wait_for(lambda: len(duties) >= 445, what="duties after the trip")
    assert not any(d.enable for d in duties[-50:])


def test_controller_wall_clock_timeout_when_the_estimate_never_comes(graph, run):
    """Lockstep: the plant waits for our duty, so sample time stands still; an estimate
    that never comes (observer process gone) trips after position_wall_timeout_s."""
    from fluxdrive_ros.wire import EstimateWire, FrameWire

    from flux_drive_msgs.msg import ControllerState, DutyCommand, PhaseFrame, RotorEstimate

    sc, r = run
    _controller(graph, sc, position_wall_timeout_s=0.5)
    duties = graph.listen(DutyCommand, "/drive/duty")
    states = graph.listen(ControllerState, "/drive/controller_state")
    fpub = graph.publisher(PhaseFrame, "/drive/frame")
    epub = graph.publisher(RotorEstimate, "/probe/estimate")
    wait_matched(fpub)
    wait_matched(epub)
    fw, ew = FrameWire(), EstimateWire("probe")
    for k in range(10):
        fpub.publish(frame_bytes(fw, r.frames[k], k))
        epub.publish(_est_bytes(ew, k))
    wait_for(lambda: len(duties) >= 10, what="duties")
    fpub.publish(frame_bytes(fw, r.frames[10], 10))
    t0 = time.monotonic()
    wait_for(lambda: len(duties) >= 11, what="the PWM-off duty")
    dt = time.monotonic() - t0
    print(f"PWM-off duty for frame 10 after {dt:.2f} s (timeout 0.5 s)")
    assert duties[10].seq == 10 and not duties[10].enable and duties[9].enable
    assert dt > 0.4  # not before its timeout (how much later depends on the machine's load)
    wait_for(lambda: len(states) >= 11, what="state")
    assert states[10].fault_reason == "stale input" and states[10].fault_code == 8


def test_controller_trips_on_a_nan_frame(graph, run):
    """A non-finite current reaches the controller: the engine's bad-sample trip, PWM off
    at once and latched."""
    from fluxdrive.drive.plant import FR_IA
    from fluxdrive_ros.wire import EstimateWire, FrameWire

    from flux_drive_msgs.msg import ControllerState, DutyCommand, PhaseFrame, RotorEstimate

    sc, r = run
    _controller(graph, sc)
    duties = graph.listen(DutyCommand, "/drive/duty")
    states = graph.listen(ControllerState, "/drive/controller_state")
    fpub = graph.publisher(PhaseFrame, "/drive/frame")
    epub = graph.publisher(RotorEstimate, "/probe/estimate")
    wait_matched(fpub)
    wait_matched(epub)
    fw, ew = FrameWire(), EstimateWire("probe")
    for k in range(30):
        fr = r.frames[k].copy()
        if k == 20:
            fr[FR_IA] = np.nan
        fpub.publish(frame_bytes(fw, fr, k))
        epub.publish(_est_bytes(ew, k))
    wait_for(lambda: len(states) >= 30 and len(duties) >= 30, what="duties")
    assert duties[19].enable and not any(d.enable for d in duties[20:])
    assert states[20].fault_code == 10
    assert states[20].fault_reason == "bad sample (NaN/inf)"
    assert states[29].fault_reason == states[20].fault_reason


def test_plant_counts_and_neutralises_malformed_duty_commands(graph, tmp_path):
    """The simulated plant in lockstep with the probe as its controller: a NaN duty runs
    that period with the PWM off, a duty of 1.7 is clamped, a repeat and a duty for a frame
    not published yet are dropped; all counted on /diagnostics."""
    from diagnostic_msgs.msg import DiagnosticArray
    from helpers_engine import make_scenario
    from spm_plant_sim.node import PlantNode

    from flux_drive_msgs.msg import DutyCommand, PhaseFrame

    sc = make_scenario(
        tmp_path,
        name="plant_bad",
        duration_s=0.01,
        speed_rpm=0.0,
        observers={"flux": {"variant": "paper"}},
    )
    frames: list = []
    diags = graph.listen(DiagnosticArray, "/diagnostics")
    dpub = graph.publisher(DutyCommand, "/drive/duty")
    sent: list = []

    from fluxdrive_ros import access, qos

    def duty_msg(seq: int, duty: list) -> DutyCommand:
        d = DutyCommand(seq=seq, duty=duty, enable=True)
        d.commander = access.mark("/probe", "/drive/duty")  # the probe is allowed
        return d

    def on_frame(m):
        frames.append(m)
        k = m.seq
        duty = {5: [np.nan, 0.5, 0.5], 6: [1.7, 0.5, -0.2]}.get(k, [0.55, 0.5, 0.45])
        dpub.publish(duty_msg(k, duty))
        if k == 7:
            dpub.publish(duty_msg(7, duty))  # repeat
            dpub.publish(duty_msg(500, duty))  # no such frame yet
        sent.append(k)

    graph.probe.create_subscription(PhaseFrame, "/drive/frame", on_frame, qos.reader("volatile"))
    graph.add(
        PlantNode,
        "plant",
        scenario=str(sc.source),
        diagnostics_period_s=0.2,
        exit_on_done=False,
        start_delay_s=0.3,
        allowed_commanders=["/probe"],
    )
    wait_for(lambda: len(frames) >= 100, what="the plant's 100 frames")
    by = {m.seq: m for m in frames}
    assert by[6].pwm_enabled and not by[7].pwm_enabled  # duty(5) acts on period 6 -> 7
    assert list(by[8].duty_applied) == [1.0, 0.5, 0.0]  # duty(6) clamped
    assert by[9].pwm_enabled
    mark = len(diags)
    wait_for(lambda: diag_status(diags, "/plant: commands", mark) is not None, what="diagnostics")
    st = diag_status(diags, "/plant: commands")
    v = values(st)
    print("plant diagnostics:", st.message, v)
    assert v["duty_nonfinite"] == "1" and v["duty_out_of_range"] == "1"
    assert v["repeated_or_backwards"] == "1" and v["unexpected_seq"] == "1"
    levels = {s.level for a in diags for s in a.status if s.name == "/plant: commands"}
    assert bytes([1]) in levels
