"""CAN log import core: .log/.asc/.blf with CAN FD sample frames survive a round trip."""

from __future__ import annotations

import sys
from pathlib import Path

import can
import numpy as np
import pytest

try:
    import fluxdrive.can.canlog  # noqa: F401
except ImportError:  # not installed: use the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))

from fluxdrive.can import canlog
from fluxdrive.can import protocol as cp
from fluxdrive.drive.plant import FR_DA, FR_DC, FR_IA, FR_IC, FR_VAB, FR_VCA, FR_VDC

# frame-row column groups (fluxdrive.drive.plant FR_*)
CUR, VLL, DUTY = slice(FR_IA, FR_IC + 1), slice(FR_VAB, FR_VCA + 1), slice(FR_DA, FR_DC + 1)

FD = cp.FRAME_INDEX


def make_frames(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.zeros((n, len(cp.FRAME_FIELDS)))
    f[:, CUR] = rng.uniform(-20, 20, (n, 3))
    f[:, VLL] = rng.uniform(-72, 72, (n, 3))
    f[:, FR_VDC] = rng.uniform(60, 80, n)
    f[:, DUTY] = rng.uniform(0, 1, (n, 3))
    f[:, FD["encoder_counts"]] = rng.integers(-(2**31), 2**31, n)
    f[:, FD["pwm_enabled"]] = 1
    f[:, FD["seq"]] = (np.arange(n) + 65_300) % 65536  # crosses the wrap
    f[:, FD["flags"]] = rng.integers(0, 2, n)
    return f


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_fd_capture_round_trip(tmp_path, suffix):
    f = make_frames(600)
    pay = cp.frames_to_fd_payloads(f)
    path = tmp_path / f"capture{suffix}"
    ts = 1_700_000_000.0 + 1e-4 * np.arange(600)
    assert canlog.write_capture(path, pay, timestamps=ts) == 600
    res = canlog.read_capture(path)
    assert res.layout == "fd"
    assert res.counts["total"] == 600 and res.counts["decoded"] == 600
    assert res.counts["malformed"] == 0 and res.counts["gaps"] == 0
    assert np.array_equal(res.frames, cp.fd_payloads_to_frames(pay))
    assert np.array_equal(res.column("seq"), f[:, FD["seq"]])
    assert np.allclose(res.timestamps, ts, atol=1e-6)


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_capture_with_gaps_malformed_and_foreign_frames(tmp_path, suffix):
    proto = cp.get_protocol()
    f = make_frames(300, seed=1)
    pay = [r.tobytes() for r in cp.frames_to_fd_payloads(f)]
    keep = [i for i in range(300) if i not in (10, 11, 12, 200)]  # 2 gaps, 4 lost
    rows: list[bytes] = [pay[i] for i in keep]
    ids = [cp.ID_SAMPLE_FD] * len(rows)
    # one truncated sample (FD length 48), one out-of-range sample, two foreign frames
    raw = proto.fd_codec.decode_raw(np.frombuffer(pay[50], np.uint8).reshape(1, 64))
    raw[0, proto.fd_codec.index["duty_a"]] = 65_535
    rows[60] = proto.fd_codec.encode_raw(raw)[0].tobytes()
    rows[70] = rows[70][:48]
    rows.insert(5, proto.encode("STATUS", {"st_protocol_version": 1, "st_decimation": 8}))
    ids.insert(5, cp.ID_STATUS)
    rows.insert(6, proto.encode("DUTY_CMD", {"cmd_seq": 3, "cmd_duty_a": 0.5}))
    ids.insert(6, cp.ID_DUTY_CMD)
    path = tmp_path / f"mixed{suffix}"
    canlog.write_capture(path, rows, arbitration_id=ids)
    res = canlog.read_capture(path)
    c = res.counts
    assert c["total"] == len(rows) and c["other"] == 2
    assert c["sample"] == len(rows) - 2 and c["malformed"] == 2
    assert c["decoded"] == len(rows) - 4
    assert c["gaps"] == 2 + 2 and c["lost"] == 4 + 2  # plus the two dropped malformed
    reasons = dict(res.reasons)
    assert any("duty_a" in r for r in reasons.values())
    assert any("wrong length 48" in r for r in reasons.values())


def test_classic_layout_capture(tmp_path):
    f = make_frames(8 * 40 + 1, seed=2)
    f[:, FD["encoder_counts"]] = np.arange(f.shape[0]) * 50_000.0  # wraps 24 bit
    dec = cp.decimate_for_classic(f, 8)
    ids, rows = [], []
    for row in dec:
        for fid, data in cp.frame_to_classic_payloads(row, {"c_armed": 1}):
            ids.append(fid)
            rows.append(data)
    path = tmp_path / "classic.blf"
    canlog.write_capture(path, rows, arbitration_id=ids, period=2.5e-5)
    res = canlog.read_capture(path)
    assert res.layout == "classic" and res.counts["decoded"] == 40
    assert res.counts["gaps"] == 0 and res.counts["malformed"] == 0
    assert np.max(np.abs(res.frames[:, CUR] - dec[:, CUR])) <= 0.0005 + 1e-12
    assert np.array_equal(res.column("encoder_counts"), dec[:, FD["encoder_counts"]])


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_sample_without_fd_flag_rejected(tmp_path, suffix):
    """A sample frame logged with the FD flag clear is malformed in every format
    (candump keeps the bytes but not the flag; .asc/.blf cut it to 8 bytes)."""
    f = make_frames(3)
    f[:, FD["seq"]] = [0, 1, 2]
    pay = cp.frames_to_fd_payloads(f)
    path = tmp_path / f"noflag{suffix}"
    with can.Logger(str(path)) as w:
        for i, r in enumerate(pay):
            w.on_message_received(
                can.Message(
                    timestamp=float(i),
                    arbitration_id=cp.ID_SAMPLE_FD,
                    is_extended_id=False,
                    is_fd=(i != 1),
                    data=r.tobytes(),
                    channel=1 if suffix == ".blf" else "can0",
                )
            )
    res = canlog.read_capture(path)
    assert res.counts["sample"] == 3 and res.counts["decoded"] == 2
    assert res.counts["malformed"] == 1 and res.counts["lost"] == 1
    assert res.reasons[0][0] == 1
    assert "FD flag" in res.reasons[0][1] or "wrong length 8" in res.reasons[0][1]


def test_unsupported_format_refused(tmp_path):
    with pytest.raises(ValueError, match="pcap"):
        canlog.read_capture(tmp_path / "x.pcap")
    with pytest.raises(ValueError, match="trc"):
        canlog.write_capture(tmp_path / "x.trc", [bytes(64)])
