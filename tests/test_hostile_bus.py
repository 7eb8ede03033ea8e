"""Hostile frames on the bench bus: only new samples reach the graph.

A forged SAMPLE_FD far ahead (a jump), repeated and replayed samples, late ones: each is
classified, counted and dropped (fluxdrive.can.protocol.SeqFilter), never handed on as a
new sample; a capture with repeats imports each sample once; a flood of foreign-id frames
on a udp_multicast bus costs no sample; a bus lost while armed latches a fault naming it.
Real python-can buses (virtual, udp_multicast on 127.0.0.1 with TTL 0), no ROS."""

from __future__ import annotations

import json
import threading
import time

import can
import numpy as np
import pytest
from fluxdrive.can.bridge import (
    BridgeConfig,
    CanBridge,
    bus_factory_from_params,
    software_bus_endpoint,
)
from fluxdrive.can.canlog import read_capture, write_capture
from fluxdrive.can.loop import new_virtual_channel
from fluxdrive.can.protocol import ID_SAMPLE_FD, SeqFilter, get_protocol
from fluxdrive.core import yamlio
from fluxdrive.drive.control import FAULT_STALE_INPUT
from fluxdrive.drive.plant import FR_SEQ

PROTO = get_protocol()


def sample(seq: int) -> can.Message:
    """A DBC-valid SAMPLE_FD with wire counter `seq`."""
    data = PROTO.encode("SAMPLE_FD", {"seq": seq % 65536, "vdc": 72.0})
    return can.Message(arbitration_id=ID_SAMPLE_FD, is_extended_id=False, is_fd=True, data=data)


def test_seq_filter_classifies_every_kind():
    f = SeqFilter(max_jump=1000)
    seqs = [*range(300), 30_300, *range(300, 400), *list(range(200)) * 3, 400, 400, 398, 403]
    keep, k = f.accept(seqs)
    st = f.stats
    # taken: 0..399, 400 and 403 (a gap of 2); the rest counted by kind, none taken
    assert list(k[keep]) == [*range(401), 403]
    assert (st.jumps, st.duplicates, st.out_of_order) == (1, 600 + 1 + 1, 0)
    assert (st.gaps, st.lost, st.rejected) == (1, 2, 602 + 1)
    # late (never taken) vs duplicate (taken before)
    f2 = SeqFilter()
    keep, _ = f2.accept([0, 1, 3, 2, 3])
    assert list(keep) == [True, True, True, False, False]
    assert (f2.stats.out_of_order, f2.stats.duplicates) == (1, 1)
    # the counter wraps; a jump the elapsed time explains is new (10 kHz, 0.5 s: 5000)
    f3 = SeqFilter(max_jump=100)
    keep, k = f3.accept([65534, 65535, 0, 5000], times=[0.0, 1e-4, 2e-4, 0.5], rate_hz=1e4)
    assert keep.all() and list(k) == [65534, 65535, 65536, 70536]
    # a stream that really went on from a jump is followed after resync_after in a row
    f4 = SeqFilter(resync_after=3)
    keep, k = f4.accept([1, 2, 3, 20_000, 20_001, 20_002, 20_003, 20_004])
    assert list(keep) == [True] * 3 + [False] * 3 + [True] * 2
    assert (f4.stats.jumps, f4.stats.resyncs) == (3, 1)
    # re-anchored (reconnect, reset): the next sample goes on forward, never back
    f4.reanchor()
    keep, k = f4.accept([5])
    assert keep[0] and k[0] > 20_004 and k[0] % 65536 == 5


def test_bridge_hands_on_only_new_samples():
    """Over a real virtual bus: a DBC-valid sample 30 000 ahead, 200 sniffed samples sent
    again three times and a late one: the graph's seq never moves backwards or jumps, no
    sample goes out twice, each kind is counted in the diagnostics."""
    ch = new_virtual_channel()
    tx = can.Bus(interface="virtual", channel=ch, fd=True)
    br = CanBridge(
        lambda: can.Bus(interface="virtual", channel=ch, fd=True),
        BridgeConfig(stale_timeout_s=30.0),
    )
    br.connect()
    out: list[int] = []

    def send(seqs) -> None:
        for s in seqs:
            tx.send(sample(s))
        out.extend(int(x) for x in br.poll(timeout=0.05, max_frames=100_000)[:, FR_SEQ])

    try:
        send(range(300))
        send([30_300])  # forged: far ahead of the stream
        assert br.newest_sample == 299
        send(range(300, 400))
        for _ in range(3):  # replay of sniffed samples, in bursts (fast path) and one by one
            send(range(200))
            send([150])
        send([398, 400])
    finally:
        br.shutdown()
        tx.shutdown()
    assert out == list(range(401)), out[-10:]
    d = br.diagnostics()
    assert d["seq_jumps"] == 1 and d["seq_duplicates"] == 3 * 201 + 1
    assert d["seq_rejected"] == 1 + 3 * 201 + 1 and d["frames_out"] == 401
    assert d["seq_gaps"] == 0 and d["fault"] == ""


def test_bridge_stale_on_dropped_samples_names_them_and_reset_restarts():
    """A drive whose counter jumped for good: every sample is dropped, the bridge goes
    stale with the reason naming the dropped samples (PWM off, latched); a reset starts
    the stream again from the next sample, forward."""
    ch = new_virtual_channel()
    tx = can.Bus(interface="virtual", channel=ch, fd=True)
    br = CanBridge(
        lambda: can.Bus(interface="virtual", channel=ch, fd=True),
        BridgeConfig(stale_timeout_s=0.1),
    )
    br.connect()
    try:
        for s in range(10):
            tx.send(sample(s))
        br.poll(timeout=0.05)
        assert br.arm()[0]
        t_end = time.monotonic() + 5.0
        s = 20_000
        while not br.fault and time.monotonic() < t_end:
            tx.send(sample(s))
            s += 1
            br.poll(timeout=0.01)
        assert "stale data" in br.fault and "jumps" in br.fault, br.fault
        assert not br.armed
        ev = [e for e in br.fault_events if e.latched]
        assert ev and ev[-1].code == FAULT_STALE_INPUT and "PWM off" in ev[-1].reason
        br.reset_fault()
        tx.send(sample(s))
        fr = br.poll(timeout=0.05)
        assert fr.shape[0] == 1 and int(fr[0, FR_SEQ]) > 9
    finally:
        br.shutdown()
        tx.shutdown()


class _DyingBus(can.BusABC):
    """A virtual bus that fails with a bus-off after `n` receives."""

    def __init__(self, channel: str, n: int):
        self.inner = can.Bus(interface="virtual", channel=channel, fd=True)
        self.n = n
        super().__init__(channel=channel)

    def send(self, msg, timeout=None):
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        self.n -= 1
        if self.n < 0:
            raise can.CanOperationError("bus-off")
        return self.inner.recv(timeout), False

    def shutdown(self):
        self.inner.shutdown()
        super().shutdown()


def test_bus_lost_while_armed_latches_its_reason():
    ch = new_virtual_channel()
    tx = can.Bus(interface="virtual", channel=ch, fd=True)
    br = CanBridge(
        lambda: _DyingBus(ch, 5), BridgeConfig(reconnect_initial_s=10.0, stale_timeout_s=30.0)
    )
    br.connect()
    try:
        tx.send(sample(0))
        br.poll(timeout=0.05)
        assert br.arm()[0]
        for _ in range(10):
            br.poll(timeout=0.01)
    finally:
        br.shutdown()
        tx.shutdown()
    assert not br.armed and "CAN bus lost while armed" in br.fault and "bus-off" in br.fault
    ev = [e for e in br.fault_events if e.latched]
    assert ev and "PWM off" in ev[-1].reason
    assert not br.arm()[0]  # no arming until a reset


def test_capture_with_repeated_samples_imports_each_once(tmp_path):
    """200 samples captured, the same 200 sent again twice (a replay on the bus): the
    import keeps 200 and counts 400 duplicates, in its counts and the bag's metadata."""
    from fluxdrive.io.bagio import bag_counts
    from fluxdrive.io.canimport import import_capture

    pay = [bytes(sample(s).data) for s in [*range(200)] * 3]
    ts = 1_700_000_000.0 + 1e-4 * np.arange(len(pay))
    log = tmp_path / "replayed.log"
    write_capture(log, pay, timestamps=ts)
    res = read_capture(log)
    assert res.counts["decoded"] == 600 and res.counts["kept"] == 200
    assert res.counts["duplicates"] == 400 and res.counts["rejected"] == 400
    assert list(res.column("seq")) == list(range(200))
    out = import_capture(log, tmp_path / "bag")
    assert out["written"] == 200 and out["duplicates"] == 400
    counts, _ = bag_counts(tmp_path / "bag")
    assert counts["/drive/frame"] == 200
    # the bag's metadata says what was left out
    info = yamlio.load_file(tmp_path / "bag" / "metadata.yaml")["rosbag2_bagfile_information"]
    seq = json.loads(info["custom_data"]["fluxdrive"])["can_import"]["sequence"]
    assert seq["duplicates"] == 400 and seq["gaps"] == 0


@pytest.mark.serial  # a timed burst: the reader must keep up with it
def test_flood_of_foreign_frames_costs_no_sample():
    """20 000 foreign-id frames in about 0.4 s on a udp_multicast bus (127.0.0.1, TTL 0)
    between the drive's samples: every sample reaches the bridge, the flood is counted."""
    pytest.importorskip("msgpack")
    group, port = software_bus_endpoint(7)
    kw = {"interface": "udp_multicast", "channel": group, "port": port, "hop_limit": 0}
    br = CanBridge(bus_factory_from_params(**kw), BridgeConfig(stale_timeout_s=30.0))
    assert br.connect()
    drive = can.Bus(fd=True, **kw)
    probe = can.Bus(fd=True, **kw)
    n_flood, n_samples = 20_000, 200
    got: list[int] = []
    stop = threading.Event()

    def read() -> None:
        while not stop.is_set() or len(got) < n_samples:
            got.extend(int(x) for x in br.poll(timeout=0.01)[:, FR_SEQ])
            if stop.is_set() and time.monotonic() > t_give_up:
                return

    t_give_up = time.monotonic() + 60.0
    th = threading.Thread(target=read, daemon=True)
    th.start()
    try:
        foreign = can.Message(arbitration_id=0x555, is_extended_id=False, data=bytes(8))
        t0 = time.monotonic()
        for i in range(n_flood):
            probe.send(foreign)
            if i % (n_flood // n_samples) == 0:
                drive.send(sample(i // (n_flood // n_samples)))
        flood_s = time.monotonic() - t0
        stop.set()
        th.join(60.0)
    finally:
        stop.set()
        br.shutdown()
        drive.shutdown()
        probe.shutdown()
    d = br.diagnostics()
    print(f"flood: {n_flood} foreign frames in {flood_s:.2f} s; samples {len(got)}")
    assert got == list(range(n_samples)), (len(got), d)
    assert d["rx_other"] == n_flood and d["seq_gaps"] == 0


def test_drive_drops_a_datagram_that_is_no_can_message():
    """A datagram on the drive's udp_multicast group and port that is no python-can message
    (another program's UDP traffic: the bench draws its port at random, and DDS's ports lie
    in the same range) is counted and dropped; the drive's frames go on, one per sample.
    Was: the drive process died with "could not unpack received message"."""
    pytest.importorskip("msgpack")
    import socket

    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
    from fluxdrive.drive.sim import DriveSetup

    sc = load_scenario(
        CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml",
        overrides={"duration_s": 0.1, "steady_window_s": [0.05, 0.1], "bench": {}},
    )
    group, port = software_bus_endpoint(11)
    kw = {"interface": "udp_multicast", "channel": group, "port": port}
    emu = DriveEmulator(DriveSetup(sc), can.Bus(fd=True, hop_limit=0, **kw), lockstep=False)
    tap = can.Bus(fd=True, hop_limit=0, **kw)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            s.sendto(b"\x00 not a CAN message", (group, kw["port"]))
        t_end = time.monotonic() + 30.0
        while not emu.stats.foreign_datagrams and time.monotonic() < t_end:
            emu.step()
        k = emu.k
        for _ in range(8 * emu.decimation):  # and it runs on
            emu.step()
        seqs, tap_dropped = [], 0
        while True:
            try:  # the tap hears the foreign datagram too
                msg = tap.recv(1.0 if not seqs else 0.2)
            except can.CanOperationError:
                tap_dropped += 1
                continue
            if msg is None:
                break
            if msg.arbitration_id == ID_SAMPLE_FD:
                seqs.append(int(PROTO.decode(ID_SAMPLE_FD, bytes(msg.data))["seq"]))
    finally:
        emu.bus.shutdown()
        tap.shutdown()
    assert emu.stats.foreign_datagrams == tap_dropped == 1
    assert emu.k == k + 8 * emu.decimation
    assert seqs == list(range(len(seqs))) and len(seqs) >= 8


def test_housekeeping_values_checked_before_use():
    """A STATUS whose value is outside the DBC's range (st_decimation 0; the range is
    1..255) is malformed: counted, and nothing of it taken as the drive's state."""
    ch = new_virtual_channel()
    tx = can.Bus(interface="virtual", channel=ch, fd=True)
    br = CanBridge(lambda: can.Bus(interface="virtual", channel=ch, fd=True))
    br.connect()
    st = PROTO.message("STATUS")
    try:
        data = st.encode({s.name: 0 for s in st.signals}, strict=False)
        tx.send(can.Message(arbitration_id=st.frame_id, is_extended_id=False, data=data))
        br.poll(timeout=0.05)
    finally:
        br.shutdown()
        tx.shutdown()
    d = br.diagnostics()
    assert d["malformed_housekeeping"] == 1 and d.get("status_rx", 0) == 0
    assert br.drive_mismatch == "" and "decimation" not in br.mcu


def test_report_window_skips_missing_rows():
    """A run's report over rows a run never received (NaN): whole electrical periods
    between the finite angles, no ValueError (was `cannot convert float NaN to integer`)."""
    from fluxdrive.analysis.metrics import whole_periods

    th = np.linspace(0.0, 5.5 * 2 * np.pi, 1101)  # 5.5 periods, 200 samples per period
    full = whole_periods(th)
    th_missing = th.copy()
    th_missing[[0, 600, 1100]] = np.nan  # the first, a middle and the last row missing
    sl = whole_periods(th_missing)
    assert full == slice(0, 1000)  # 5 whole periods
    # from the first finite angle (sample 1): 5 periods end at sample 1001
    assert sl == slice(0, 1001)
    assert whole_periods(np.full(10, np.nan)) == slice(0, 10)


def test_report_over_a_lost_sample_names_no_fault():
    """A sample lost on the bench bus is a NaN row in every array of the run: the report's
    fault code is taken over the rows that arrived (was `int(nan)`: a traceback after a
    flood lost one sample), and a drive that never faulted reports FAULT_NONE."""
    import dataclasses

    from fluxdrive.analysis.metrics import compute
    from fluxdrive.drive.control import CO_FAULT, FAULT_NONE
    from fluxdrive.drive.scenario import load_scenario, scenario_path
    from fluxdrive.drive.sim import run_scenario

    sc = load_scenario(scenario_path("paper_2pct_150load"))
    sc = dataclasses.replace(sc, duration_s=1.5, steady_window_s=(1.0, 1.5))
    res = run_scenario(sc, progress=False)
    whole = compute(res)
    assert whole["fault_code"] == FAULT_NONE
    k = res.ctrl.shape[0] // 2
    res.ctrl[k, :] = np.nan  # the controller's state of one sample never reached the bag
    assert np.isnan(res.ctrl[k, CO_FAULT])
    lost = compute(res)
    assert lost["fault_code"] == FAULT_NONE
