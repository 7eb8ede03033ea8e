"""The ROS side of the environment: the venv's rclpy, the colcon-built flux_drive_msgs,
rosbags agreeing with rclpy on every message definition, and a real publish/subscribe.

Runs in the environment of tools/env.sh (``./fluxdrive test``, or ``source tools/env.sh``
then ``python -m pytest``); fails with a hint when that environment is missing.
"""

from __future__ import annotations

import math
import os
import random
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain

ROOT = Path(__file__).resolve().parents[1]
MSG_PKG = ROOT / "src" / "flux_drive_msgs"
MSG_NAMES = sorted(p.stem for p in (MSG_PKG / "msg").glob("*.msg"))
SRV_NAMES = sorted(p.stem for p in (MSG_PKG / "srv").glob("*.srv"))
HINT = "run through ./fluxdrive test, or `source tools/env.sh` first (and tools/bootstrap.sh)"

try:
    import rclpy
    from rclpy.serialization import deserialize_message, serialize_message

    import flux_drive_msgs.msg as fmsg
    import flux_drive_msgs.srv as fsrv
except ImportError as exc:  # pragma: no cover - environment problem, reported by the tests
    IMPORT_ERROR: ImportError | None = exc
else:
    IMPORT_ERROR = None


@pytest.fixture(autouse=True)
def _require_ros_env():
    if IMPORT_ERROR is not None:
        pytest.fail(f"cannot import rclpy / flux_drive_msgs ({IMPORT_ERROR}); {HINT}")


# --------------------------------------------------------------------------- helpers
def _fill(msg, rng: random.Random):
    """Set every field of an rclpy message to a non-default value, by its declared type."""
    for name, typ in msg.get_fields_and_field_types().items():
        m = re.fullmatch(r"(\w+)\[(\d+)\]", typ)
        if typ == "std_msgs/Header":
            hdr = getattr(msg, name)
            hdr.stamp.sec = rng.randrange(0, 2**31)
            hdr.stamp.nanosec = rng.randrange(0, 10**9)
            hdr.frame_id = f"frame_{rng.randrange(1000)}"
        elif m and m.group(1) == "double":
            setattr(msg, name, [rng.uniform(-1e3, 1e3) for _ in range(int(m.group(2)))])
        elif typ == "double":
            setattr(msg, name, rng.uniform(-1e3, 1e3))
        elif typ in ("uint8", "uint32", "uint64"):
            bits = int(typ[4:])
            setattr(msg, name, rng.randrange(1, 2**bits))
        elif typ == "boolean":
            setattr(msg, name, True)
        elif typ == "string":
            setattr(msg, name, f"{name}-{rng.randrange(10**6)}-µ")  # non-ASCII on purpose
        else:  # a new field type: extend the filler, do not let it pass untested
            raise AssertionError(f"{type(msg).__name__}.{name}: no filler for type {typ!r}")
    return msg


def _plain(obj):
    """rclpy or rosbags message -> nested plain Python values, for comparison."""
    if isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, np.ndarray):
        return [_plain(x) for x in obj.tolist()]
    if isinstance(obj, (list, tuple)):
        return [_plain(x) for x in obj]
    if hasattr(obj, "get_fields_and_field_types"):  # rclpy
        return {k: _plain(getattr(obj, k)) for k in obj.get_fields_and_field_types()}
    if hasattr(obj, "__dataclass_fields__"):  # rosbags
        return {
            k: _plain(getattr(obj, k))
            for k in obj.__dataclass_fields__
            if k != "__msgtype__" and not k.isupper()
        }
    raise TypeError(type(obj))


def _rosbags_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in MSG_NAMES:
        text = (MSG_PKG / "msg" / f"{name}.msg").read_text()
        types.update(get_types_from_msg(text, f"flux_drive_msgs/msg/{name}"))
    store.register(types)
    return store


def _msg_types():
    """(type name, rclpy class) for every message (services never go into bags)."""
    return [(f"flux_drive_msgs/msg/{n}", getattr(fmsg, n)) for n in MSG_NAMES]


def _srv_types():
    return [c for n in SRV_NAMES for c in (getattr(fsrv, n).Request, getattr(fsrv, n).Response)]


# ------------------------------------------------------------------------ (a) rclpy
def test_environment_is_the_projects():
    assert Path(sys.prefix).resolve() == (ROOT / ".venv").resolve(), HINT
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    assert Path(fmsg.__file__).resolve().is_relative_to(ROOT / ".ws"), fmsg.__file__


def test_expected_interfaces_exist():
    assert MSG_NAMES == sorted(
        [
            "ControllerState",
            "CurrentReference",
            "DriveFault",
            "DutyCommand",
            "ParameterMarker",
            "PhaseFrame",
            "PlantTruth",
            "RotorEstimate",
            "RunDone",
        ]
    )
    assert SRV_NAMES == ["Arm", "ResetFault"]
    assert fmsg.PhaseFrame.STATUS_SENSOR_CLIP == 1
    assert fmsg.PhaseFrame.STATUS_SIMULATED == 2
    assert fmsg.ControllerState.MODE_CLOSED_LOOP == 3
    assert fmsg.DriveFault.BAD_SAMPLE == 10


def test_phase_frame_round_trip_rclpy():
    f = fmsg.PhaseFrame()
    f.header.stamp.sec, f.header.stamp.nanosec = 12, 345_600_000
    f.header.frame_id = "plant"
    f.seq = 2**40 + 7
    f.i_abc = [1.25, -0.5, -0.75]
    f.v_ll = [24.0, -12.5, -11.5]
    f.vdc = 48.0
    f.duty_applied = [0.5, 0.25, 0.75]
    f.pwm_enabled = True
    f.encoder_counts = 123456.0
    f.status_flags = fmsg.PhaseFrame.STATUS_SIMULATED | fmsg.PhaseFrame.STATUS_SENSOR_CLIP
    raw = serialize_message(f)
    g = deserialize_message(raw, fmsg.PhaseFrame)
    assert g == f
    assert g.seq == 2**40 + 7 and g.status_flags == 3
    np.testing.assert_array_equal(g.i_abc, [1.25, -0.5, -0.75])
    assert isinstance(g.i_abc, np.ndarray) and g.i_abc.dtype == np.float64


def test_every_type_round_trips_rclpy():
    rng = random.Random(1)
    for cls in [c for _, c in _msg_types()] + _srv_types():
        m = _fill(cls(), rng)
        assert deserialize_message(serialize_message(m), cls) == m, cls.__name__


# ---------------------------------------------------------------------- (b) rosbags
def test_rosbags_parses_definitions_and_hashes_match_rosidl():
    store = _rosbags_typestore()
    share = ROOT / ".ws" / "install" / "share" / "flux_drive_msgs"
    import json

    for name in MSG_NAMES:
        tname = f"flux_drive_msgs/msg/{name}"
        assert tname in store.types
        hashes = json.loads((share / "msg" / f"{name}.json").read_text())["type_hashes"]
        want = next(h["hash_string"] for h in hashes if h["type_name"] == tname)
        assert store.hash_rihs01(tname) == want, f"{name}: rosbags and rosidl disagree"


def test_cdr_bytes_agree_between_rclpy_and_rosbags():
    store = _rosbags_typestore()
    rng = random.Random(2)
    for tname, cls in _msg_types():
        for _ in range(3):
            m = _fill(cls(), rng)
            raw = bytes(serialize_message(m))
            # rclpy -> rosbags
            rb = store.deserialize_cdr(raw, tname)
            assert _plain(rb) == _plain(m), tname
            # rosbags -> rclpy. Compare values, not bytes: Fast-CDR leaves padding bytes
            # uninitialised (whatever was in the buffer), rosbags writes zeros there.
            raw2 = bytes(store.serialize_cdr(rb, tname))
            assert len(raw2) == len(raw), tname
            assert deserialize_message(raw2, cls) == m, tname
            assert _plain(store.deserialize_cdr(raw2, tname)) == _plain(m), tname


def _constants(cls) -> dict:
    names = [k for k in dir(cls) if re.fullmatch(r"[A-Z][A-Z0-9_]*", k) and k != "SLOT_TYPES"]
    return {k: getattr(cls, k) for k in names}


def test_constants_agree_between_rclpy_and_rosbags():
    store = _rosbags_typestore()
    for tname, cls in _msg_types():
        assert _constants(store.types[tname]) == _constants(cls), tname
    # the message's fault codes are the engine's, one for one
    from fluxdrive.drive.control import FAULT_NAMES

    assert sorted(_constants(fmsg.DriveFault).values()) == sorted(FAULT_NAMES)


def test_mcap_bag_readable_by_rosbags_and_mcap_ros2(tmp_path):
    from mcap_ros2.reader import read_ros2_messages
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = _rosbags_typestore()
    rng = random.Random(3)
    frames = [_fill(fmsg.PhaseFrame(), rng) for _ in range(5)]
    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/phase_frame", "flux_drive_msgs/msg/PhaseFrame", typestore=store)
        for k, f in enumerate(frames):
            w.write(conn, 1_000_000 * (k + 1), bytes(serialize_message(f)))

    with AnyReader([bag]) as r:  # no typestore given: definitions come from the bag
        got = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages()]
    assert [_plain(g) for g in got] == [_plain(f) for f in frames]

    (mcap_file,) = bag.glob("*.mcap")
    seen = list(read_ros2_messages(str(mcap_file)))
    assert len(seen) == len(frames)
    for s, f in zip(seen, frames, strict=True):
        assert s.ros_msg.seq == f.seq
        assert list(s.ros_msg.i_abc) == list(f.i_abc)
        assert s.ros_msg.header.frame_id == f.header.frame_id


# ------------------------------------------------------------------ (c) pub / sub
def test_publish_subscribe_localhost(monkeypatch):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain_id = domain(17)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    try:
        pub_node = rclpy.create_node("env_test_pub", context=ctx)
        sub_node = rclpy.create_node("env_test_sub", context=ctx)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        got = []
        sub_node.create_subscription(fmsg.PhaseFrame, "env_test/phase_frame", got.append, qos)
        pub = pub_node.create_publisher(fmsg.PhaseFrame, "env_test/phase_frame", qos)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(pub_node)
        ex.add_node(sub_node)

        deadline = time.monotonic() + 10.0
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert pub.get_subscription_count() >= 1, "subscriber never matched"

        sent = fmsg.PhaseFrame(seq=42, vdc=48.0, i_abc=[1.0, -0.5, -0.5], pwm_enabled=True)
        sent.status_flags = fmsg.PhaseFrame.STATUS_SIMULATED
        pub.publish(sent)
        while not got and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert got, "no message received within 10 s"
        assert got[0] == sent
        assert ctx.get_domain_id() == domain_id
        ex.shutdown()
        pub_node.destroy_node()
        sub_node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


def test_subprocess_inherits_a_working_ros_env():
    """A child started with the parent's full environment imports the workspace packages."""
    code = (
        "import flux_drive_msgs.msg as m, rclpy; "
        "from rclpy.serialization import serialize_message as s; "
        "print(len(s(m.DutyCommand(seq=1))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        env=dict(os.environ),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) > 0
    assert not math.isnan(float(out.stdout.strip()))
