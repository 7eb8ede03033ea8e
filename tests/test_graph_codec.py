"""The graph's hand-rolled CDR codec (fluxdrive_ros.cdr) against rclpy's serialiser, for
every flux_drive_msgs message, and the engine-row <-> message round trips (fluxdrive_ros.wire)
that the bit-exactness of graph runs rests on."""

from __future__ import annotations

import random
import re

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

import flux_drive_msgs.msg as fm  # noqa: E402

MSGS = [
    "PhaseFrame",
    "PlantTruth",
    "RotorEstimate",
    "DutyCommand",
    "ControllerState",
    "DriveFault",
    "ParameterMarker",
    "CurrentReference",
]


def _get(msg, path):
    obj = msg
    for part in path.split("."):
        m = re.fullmatch(r"(\w+)\[(\d+)\]", part)
        obj = getattr(obj, m.group(1))[int(m.group(2))] if m else getattr(obj, part)
    return obj


def _set(msg, path, v):
    parts = path.split(".")
    obj = msg
    for part in parts[:-1]:
        obj = getattr(obj, part)
    m = re.fullmatch(r"(\w+)\[(\d+)\]", parts[-1])
    if m:
        getattr(obj, m.group(1))[int(m.group(2))] = v
    else:
        setattr(obj, parts[-1], v)


def _value(kind: str, rng: random.Random):
    if kind == "float64":
        return rng.choice([rng.uniform(-1e3, 1e3), 0.0, -0.0, 1e-300, float("inf")])
    if kind == "bool":
        return bool(rng.randrange(2))
    if kind == "int32":
        return rng.randrange(-(2**31), 2**31)
    bits = {"uint8": 8, "uint32": 32, "uint64": 64}[kind]
    return rng.randrange(0, 2**bits)


@pytest.mark.parametrize("name", MSGS)
def test_codec_matches_rclpy(name):
    from fluxdrive_ros.cdr import Codec, Decoder

    rng = random.Random(name)
    tn = f"flux_drive_msgs/msg/{name}"
    string_paths = [lf.path for lf in Codec(tn).leaves if lf.kind == "string"]
    dec = Decoder(tn)
    for _ in range(25):
        strings = {p: "x" * rng.randrange(0, 11) + rng.choice(["", "µ"]) for p in string_paths}
        c = Codec(tn, strings)
        msg = getattr(fm, name)()
        vals = []
        for lf in c.leaves:
            v = strings[lf.path] if lf.kind == "string" else _value(lf.kind, rng)
            if lf.kind != "string":
                vals.append(v)
            _set(msg, lf.path, v)
        ref = serialize_message(msg)
        mine = c.pack(*vals)
        # same size and same values; padding bytes are not compared (Fast-CDR leaves them
        # uninitialised)
        assert len(ref) == len(mine) == c.size
        back = deserialize_message(mine, getattr(fm, name))
        for lf in c.leaves:
            a, b = _get(back, lf.path), _get(msg, lf.path)
            assert a == b or (a != a and b != b), (lf.path, a, b)
        assert dec.decode(ref) == tuple(vals)
        assert c.unpack(ref) == tuple(vals)


def test_rows_survive_messages_bit_for_bit():
    from fluxdrive.drive.control import CO_DA, CO_EN, CO_FAULT, CO_MODE, CO_N
    from fluxdrive.drive.observers import ES_N, ES_VALID
    from fluxdrive.drive.plant import FR_EN, FR_FLAGS, FR_N, FR_SEQ, TR_N, TR_T, TR_THETA_E
    from fluxdrive.io.messages import RowCodec, row_codec
    from fluxdrive_ros.wire import ControlWire, EstimateWire, FrameWire, Stamp, TruthWire

    rng = np.random.default_rng(3)
    st = Stamp(1e-4)
    assert st(123456) == (12, 345600000)
    for k in range(50):
        fr = rng.normal(size=FR_N) * 10
        fr[FR_EN] = float(k % 2)
        fr[FR_SEQ] = k
        fr[FR_FLAGS] = float(k % 2)
        fw = FrameWire()
        out = np.zeros(FR_N)
        assert fw.unpack(fw.pack(fr, *st(k)), out) == k
        assert np.array_equal(out, fr)
        rc = row_codec("flux_drive_msgs/msg/PhaseFrame")
        assert np.array_equal(rc.row(rc.decoder.decode(fw.pack(fr, *st(k)))), fr)
        tr = rng.normal(size=TR_N)
        tr[TR_THETA_E] = abs(tr[TR_THETA_E]) % 6.28
        tw = TruthWire()
        got = row_codec("flux_drive_msgs/msg/PlantTruth").row(
            tw.rc.decoder.decode(tw.pack(tr, k, *st(k)))
        )
        got[TR_T] = tr[TR_T]  # not on the wire (t = seq Ts)
        assert np.array_equal(got, tr)
        es = rng.normal(size=ES_N)
        es[ES_VALID] = float(k % 2)
        ew = EstimateWire("flux_measured")
        row = np.zeros(ES_N)
        assert ew.unpack(ew.pack(es, k, *st(k)), row) == k
        assert np.array_equal(row, es)
        co = rng.normal(size=CO_N)
        co[CO_DA : CO_DA + 3] = rng.uniform(size=3)
        co[CO_EN] = 1.0
        co[CO_MODE] = 3.0
        co[CO_FAULT] = float(k % 3 == 0) * 7 + float(k == 3) * 30  # 30: an unknown code
        cw = ControlWire(commander="/controller#0123")
        got = np.zeros(CO_N)
        RowCodec("flux_drive_msgs/msg/DutyCommand").unpack(cw.pack_duty(co, k, *st(k)), got)
        sb = cw.pack_state(co, k, *st(k))
        RowCodec("flux_drive_msgs/msg/ControllerState").unpack(sb, got)
        assert np.array_equal(got, co)
        # the fault travels as a number; its text is the name (one rule for unknown codes)
        reason = (
            RowCodec("flux_drive_msgs/msg/ControllerState")
            .decoder.codec_for(sb)
            .strings["fault_reason"]
        )
        assert (
            reason == {0: "", 7: "position estimate not finite", 37: "fault 37"}[int(co[CO_FAULT])]
        )


def test_estimate_blocks_pack_the_same_bytes_as_one_by_one():
    """A shadow's block of estimates packed in one numpy pass gives the very messages
    `pack` gives row by row -- also with NaN, signed zeros, huge values and stamps across
    a second boundary."""
    from fluxdrive.drive.observers import ES_N, ES_VALID
    from fluxdrive_ros.wire import EstimateWire, Stamp

    rng = np.random.default_rng(7)
    stamp = Stamp(1e-4)
    seqs = np.arange(99_990, 100_050)
    n = len(seqs)
    es = rng.normal(size=(n, ES_N)) * 10.0 ** rng.integers(-8, 8, size=(n, ES_N))
    es[3, :] = np.nan
    es[4, :] = -0.0
    es[5, :] = 1e300
    es[:, ES_VALID] = rng.integers(0, 2, n)
    ew = EstimateWire("emf_measured", "f", graph_id=12345)
    ks = [int(k) for k in seqs]
    block = ew.pack_block(es, seqs, stamp.ns_block(seqs))
    assert block == [ew.pack(es[i], k, *stamp(k)) for i, k in enumerate(ks)]


def _odd_rows(rng, n: int, width: int) -> np.ndarray:
    """Rows of every kind of value a row may hold: NaN, signed zeros, huge and tiny."""
    rows = rng.normal(size=(n, width)) * 10.0 ** rng.integers(-8, 8, size=(n, width))
    rows[3, :] = np.nan
    rows[4, :] = -0.0
    rows[5, :] = 1e300
    return rows


def test_frame_blocks_pack_the_same_bytes_as_one_by_one():
    """PhaseFrames packed in one numpy pass (the bits each frame carries: its own flags
    kept to the travelling ones, the publisher's, a per-frame extra) are the messages
    `pack` gives one by one."""
    from fluxdrive.drive.plant import FR_EN, FR_ENC, FR_FLAGS, FR_N, FR_SEQ
    from fluxdrive.io.messages import STATUS_SIMULATED, STATUS_STALE_COMMAND
    from fluxdrive_ros.wire import FrameWire, Stamp

    rng = np.random.default_rng(11)
    stamp = Stamp(2.5e-4)
    seqs = np.arange(39_990, 40_050)
    n = len(seqs)
    fr = _odd_rows(rng, n, FR_N)
    fr[:, FR_EN] = rng.integers(0, 2, n)
    fr[:, FR_ENC] = np.round(fr[:, FR_ENC])
    fr[:, FR_FLAGS] = rng.integers(0, 64, n)
    fr[:, FR_SEQ] = seqs
    xf = rng.choice([0, STATUS_STALE_COMMAND], n)
    fw = FrameWire("bench", extra_flags=STATUS_SIMULATED, graph_id=77)
    block = fw.rc.pack_block(fr, seqs, stamp.ns_block(seqs), xf)
    assert block == [fw.pack(fr[i], *stamp(int(k)), int(xf[i])) for i, k in enumerate(seqs)]


@pytest.mark.parametrize("mtype", ["frame", "estimate", "duty", "state", "truth"])
def test_rows_delivered_in_process_are_the_rows_the_messages_give(mtype):
    """A reader in the publisher's process gets `wire_row` of the publisher's row instead of
    the bytes (fluxdrive_ros.intra): it must be, bit for bit, the row `unpack` fills from the
    message `pack` makes -- in every column the message carries (NaN in the others)."""
    from fluxdrive.drive.control import CO_FAULT, CO_N
    from fluxdrive.drive.observers import ES_N, ES_VALID
    from fluxdrive.drive.plant import FR_EN, FR_FLAGS, FR_N, TR_N, TR_THETA_E
    from fluxdrive.io import topics
    from fluxdrive.io.messages import MAPS, STATUS_SIMULATED, RowCodec
    from fluxdrive_ros.wire import Stamp

    rng = np.random.default_rng(5)
    kind = {
        "frame": (topics.T_FRAME, FR_N),
        "estimate": (topics.T_ESTIMATE, ES_N),
        "duty": (topics.T_DUTY, CO_N),
        "state": (topics.T_STATE, CO_N),
        "truth": (topics.T_TRUTH, TR_N),
    }
    mt, width = kind[mtype]
    rc = RowCodec(mt, flags_or=STATUS_SIMULATED if mtype == "frame" else 0, graph_id=3)
    carried = {c for _, c in MAPS[mt][0]}
    if mtype == "frame":
        from fluxdrive.drive.plant import FR_SEQ

        carried.add(FR_SEQ)
    rows = _odd_rows(rng, 40, width)
    rows[:, {"frame": FR_EN, "estimate": ES_VALID}.get(mtype, 0)] = rng.uniform(0, 1, 40)
    if mtype == "frame":
        rows[:, FR_FLAGS] = rng.integers(0, 64, 40)
    if mtype == "state":
        rows[:, CO_FAULT] = 0.0
        from fluxdrive.drive.control import CO_MODE

        rows[:, CO_MODE] = rng.integers(0, 5, 40)
    if mtype == "truth":
        rows[:, TR_THETA_E] = rng.uniform(-7, 7, 40)
    stamp = Stamp(1e-4)
    for i, row in enumerate(rows):
        if mtype == "state" and not np.isfinite(row).all():
            continue  # integer fields of a state are whole numbers: NaN does not pack
        k = 1_000 + i
        xf = 16 if i % 3 == 0 else 0
        args = (xf,) if mtype == "frame" else ()
        got = rc.wire_row(row, k, *args)
        via = np.full(width, -1.0)
        rc.unpack(rc.pack(row, k, *stamp(k), *args), via)
        for c in range(width):
            if c in carried:
                a, b = got[c], via[c]
                assert a == b or (np.isnan(a) and np.isnan(b)), (i, c, a, b)
                assert np.signbit(got[c]) == np.signbit(via[c]), (i, c)
            else:
                assert np.isnan(got[c]), (i, c)
