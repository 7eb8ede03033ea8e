"""CAN protocol layer: DBC, numpy codec vs cantools, validation, seq gaps, classic layout."""

from __future__ import annotations

import sys
from pathlib import Path

import cantools
import numpy as np
import pytest

try:
    import fluxdrive.can.protocol  # noqa: F401
except ImportError:  # not installed: use the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))

from fluxdrive.can import protocol as cp
from fluxdrive.drive.plant import (
    FR_DA,
    FR_DC,
    FR_IA,
    FR_IC,
    FR_VAB,
    FR_VCA,
    FR_VDC,
)

# frame-row column groups (fluxdrive.drive.plant FR_*)
CUR, VLL, DUTY = slice(FR_IA, FR_IC + 1), slice(FR_VAB, FR_VCA + 1), slice(FR_DA, FR_DC + 1)

FD = cp.FRAME_INDEX


@pytest.fixture(scope="module")
def proto() -> cp.FluxdriveProtocol:
    return cp.get_protocol()


def random_raw(msg, n: int, rng: np.random.Generator) -> np.ndarray:
    """Random raw values over each signal's full bit range (ignores DBC min/max)."""
    cols = []
    for s in msg.signals:
        if s.is_signed:
            cols.append(rng.integers(-(1 << (s.length - 1)), 1 << (s.length - 1), n))
        else:
            cols.append(rng.integers(0, 1 << s.length, n, dtype=np.uint64).astype(np.int64))
    return np.stack(cols, axis=1)


def random_in_range(msg, n: int, rng: np.random.Generator) -> np.ndarray:
    """Random physical values on each signal's grid, inside the DBC [min, max]."""
    cols = []
    for s in msg.signals:
        lo_raw = -(1 << (s.length - 1)) if s.is_signed else 0
        hi_raw = (1 << (s.length - 1)) - 1 if s.is_signed else (1 << s.length) - 1
        if s.minimum is not None:
            lo_raw = max(lo_raw, int(np.ceil((s.minimum - s.offset) / s.scale)))
        if s.maximum is not None:
            hi_raw = min(hi_raw, int(np.floor((s.maximum - s.offset) / s.scale)))
        raw = rng.integers(lo_raw, hi_raw + 1, n)
        cols.append(raw * s.scale + s.offset)
    return np.stack(cols, axis=1)


# --------------------------------------------------------------------------- DBC


def test_dbc_messages_and_priorities(proto):
    ids = {m.name: m.frame_id for m in proto.db.messages}
    # the ids themselves are generated (fluxdrive.core.protocol_constants): only their order
    assert all(i < 0x800 for i in ids.values()), "11-bit ids"
    # safety > duty/reference deadline > telemetry > housekeeping (lower ID wins)
    assert ids["FAULT"] < ids["ARM_MODE"] < ids["DUTY_CMD"] < ids["SAMPLE_FD"] < ids["STATUS"]
    assert ids["DUTY_CMD"] < ids["HOST_REF"] < ids["SAMPLE_FD"]
    fd = proto.sample_fd
    assert fd.is_fd and fd.length == 64
    ref = proto.message("HOST_REF")
    assert ref.is_fd and ref.length == 12
    fd_msgs = (fd, ref)
    assert all(not m.is_fd and m.length <= 8 for m in proto.db.messages if m not in fd_msgs)
    for m in proto.db.messages:
        assert m.comment, m.name
        for s in m.signals:
            assert s.comment, (m.name, s.name)
    units = {s.name: s.unit for s in fd.signals}
    assert units["i_a"] == "A" and units["v_ab"] == "V" and units["vdc"] == "V"
    assert fd.get_signal_by_name("seq").length >= 16
    assert fd.get_signal_by_name("encoder").length == 32
    assert fd.get_signal_by_name("encoder").is_signed
    assert proto.classic_decimation == 8 and proto.protocol_version == cp.PROTOCOL_VERSION


def test_dbc_path_override(tmp_path, monkeypatch):
    src = cp.default_dbc_path().read_text()
    alt = tmp_path / "alt.dbc"
    alt.write_text(src.replace('BA_ "ClassicDecimation" 8;', 'BA_ "ClassicDecimation" 4;'))
    assert cp.FluxdriveProtocol(alt).classic_decimation == 4
    monkeypatch.setenv(cp.DBC_ENV_VAR, str(alt))
    assert cp.default_dbc_path() == alt
    with pytest.raises(FileNotFoundError):
        cp.load_database(tmp_path / "missing.dbc")


# --------------------------------------------------------------------------- codec


@pytest.mark.parametrize("name", [
    "SAMPLE_FD", "DUTY_CMD", "ARM_MODE", "FAULT", "STATUS", "HOST_HEARTBEAT",
    "SAMPLE_C_CUR", "SAMPLE_C_VLT", "SAMPLE_C_DUTY", "SAMPLE_C_AUX",
])  # fmt: skip
def test_numpy_codec_matches_cantools(proto, name):
    rng = np.random.default_rng(42)
    msg = proto.message(name)
    codec = cp.NumpyCodec(msg)
    n = 300
    # raw-level: any bit pattern decodes identically
    raw = random_raw(msg, n, rng)
    pay = codec.encode_raw(raw)
    assert np.array_equal(codec.decode_raw(pay), raw)
    dec = codec.decode(pay)
    for i in range(n):
        ref = msg.decode(pay[i].tobytes(), decode_choices=False, scaling=True)
        assert np.array_equal(dec[i], [float(ref[s]) for s in codec.names])
    # physical level: in-range values encode to the same bytes as cantools (strict)
    vals = random_in_range(msg, n, rng)
    # add sub-LSB noise so rounding is exercised
    scales = np.array([s.scale for s in msg.signals])
    noisy = vals + rng.uniform(-0.49, 0.49, vals.shape) * scales
    lo = np.array([s.minimum for s in msg.signals])
    hi = np.array([s.maximum for s in msg.signals])
    noisy = np.clip(noisy, lo, hi)
    pay2 = codec.encode(noisy)
    for i in range(n):
        ref = msg.encode(dict(zip(codec.names, noisy[i].tolist(), strict=True)), strict=True)
        assert pay2[i].tobytes() == ref
    assert np.array_equal(codec.decode(pay2), codec.decode(codec.encode(vals)))


SYNTH_DBC = """VERSION ""
BS_:
BU_: A B
BO_ 291 ODD: 16 A
 SG_ le_odd : 3|13@1- (0.5,-2) [-4098|4093] "x" B
 SG_ be_u : 23|12@0+ (0.25,1) [1|1024.75] "y" B
 SG_ be_s : 37|21@0- (0.001,0) [-1048.576|1048.575] "z" B
 SG_ flt : 64|32@1- (1,0) [-1e6|1e6] "" B
 SG_ le_wide : 96|31@1+ (1,0) [0|2147483647] "" B
SIG_VALTYPE_ 291 flt : 1;
"""


def test_codec_generated_from_dbc_handles_any_layout():
    """Motorola byte order, odd offsets, offsets/scales and IEEE floats: the generator
    takes everything from the signal definitions."""
    db = cantools.database.load_string(SYNTH_DBC, database_format="dbc")
    msg = db.get_message_by_name("ODD")
    codec = cp.NumpyCodec(msg)
    rng = np.random.default_rng(7)
    n = 400
    vals = random_in_range(msg, n, rng)
    vals[:, codec.index["flt"]] = rng.uniform(-1e6, 1e6, n).astype(np.float32)
    pay = codec.encode(vals)
    dec = codec.decode(pay)
    for i in range(n):
        ref_bytes = msg.encode(dict(zip(codec.names, vals[i].tolist(), strict=True)))
        assert pay[i].tobytes() == ref_bytes
        ref = msg.decode(ref_bytes, decode_choices=False)
        assert np.array_equal(dec[i], [float(ref[s]) for s in codec.names])
    assert np.array_equal(dec, vals)


# --------------------------------------------------------------------------- frames


def make_frames(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.zeros((n, len(cp.FRAME_FIELDS)))
    f[:, CUR] = rng.uniform(-20, 20, (n, 3))
    f[:, VLL] = rng.uniform(-72, 72, (n, 3))
    f[:, FR_VDC] = rng.uniform(60, 80, n)
    f[:, DUTY] = rng.uniform(0, 1, (n, 3))
    f[:, FD["encoder_counts"]] = rng.integers(-(2**31), 2**31, n)
    f[:, FD["pwm_enabled"]] = rng.integers(0, 2, n)
    f[:, FD["seq"]] = np.arange(n) + 65_000  # crosses the 16-bit wrap
    f[:, FD["flags"]] = rng.integers(0, 2, n)  # bit 0: ADC clipped
    return f


def test_frame_round_trip_quantisation(proto):
    f = make_frames(2000)
    pay = cp.frames_to_fd_payloads(f)
    assert pay.shape == (2000, 64) and pay.dtype == np.uint8
    back = cp.fd_payloads_to_frames(pay)
    lsb = {"i": 0.001, "v": 0.001, "vdc": 0.002, "duty": 2e-5}
    assert np.max(np.abs(back[:, CUR] - f[:, CUR])) <= lsb["i"] / 2 + 1e-12
    assert np.max(np.abs(back[:, VLL] - f[:, VLL])) <= lsb["v"] / 2 + 1e-12
    assert np.max(np.abs(back[:, FR_VDC] - f[:, FR_VDC])) <= lsb["vdc"] / 2 + 1e-12
    assert np.max(np.abs(back[:, DUTY] - f[:, DUTY])) <= lsb["duty"] / 2 + 1e-12
    for name in ("pwm_enabled", "encoder_counts", "flags"):
        assert np.array_equal(back[:, FD[name]], f[:, FD[name]])
    assert np.array_equal(back[:, FD["seq"]], np.mod(f[:, FD["seq"]], 65536))
    # decode -> encode -> decode is exact (values on the grid)
    assert np.array_equal(cp.fd_payloads_to_frames(cp.frames_to_fd_payloads(back)), back)
    # single-frame API == vectorised, and == cantools
    one = cp.frame_to_fd_payload(f[5], {"t_mcu": 0.0123, "armed": 1, "cmd_seq_applied": 7})
    d = proto.decode("SAMPLE_FD", one)
    assert d["armed"] == 1 and d["cmd_seq_applied"] == 7 and d["t_mcu"] == pytest.approx(0.0123)
    assert d["i_a"] == back[5, FD["i_a"]] and d["encoder"] == back[5, FD["encoder_counts"]]
    assert np.array_equal(cp.fd_payloads_to_frames([one])[0], back[5])
    # duty 1.0 and 0.0 survive exactly
    g = f[:3].copy()
    g[:, DUTY] = [[1.0, 0.0, 0.5]] * 3
    gb = cp.fd_payloads_to_frames(cp.frames_to_fd_payloads(g))
    assert np.array_equal(gb[:, DUTY], g[:, DUTY])


def test_encoder_and_seq_wrap(proto):
    f = make_frames(4)
    f[:, FD["seq"]] = [65535, 65536, 65537, 131072 + 5]
    f[:, FD["encoder_counts"]] = [2**31 - 1, 2**31, -(2**31) - 1, 5]
    back = cp.fd_payloads_to_frames(cp.frames_to_fd_payloads(f))
    assert back[:, FD["seq"]].tolist() == [65535, 0, 1, 5]
    assert back[:, FD["encoder_counts"]].tolist() == [2**31 - 1, -(2**31), 2**31 - 1, 5]


# --------------------------------------------------------------------------- validation


def test_malformed_frames_flagged_with_reasons(proto):
    f = make_frames(10)
    pay = cp.frames_to_fd_payloads(f)
    codec = proto.fd_codec
    rows = [r.tobytes() for r in pay]
    rows[1] = rows[1][:63]  # wrong DLC
    rows[2] = rows[2][:8]  # classic-size frame
    rows[3] = b""  # empty
    bad = pay.copy()
    raw = codec.decode_raw(bad)
    raw[4, codec.index["duty_b"]] = 60_000  # 1.2 > 1
    raw[5, codec.index["i_c"]] = -30_000  # -30 A < -25 A
    raw[6, codec.index["vdc"]] = 65_000  # 130 V > 100 V
    raw[7, codec.index["v_ab"]] = 2_000_000  # 2000 V
    enc = codec.encode_raw(raw)
    for i in (4, 5, 6, 7):
        rows[i] = enc[i].tobytes()
    frames, res = proto.decode_fd(rows)
    rep = res.report
    assert rep.valid.tolist() == [True, False, False, False, False, False, False, False,
                                  True, True]  # fmt: skip
    assert rep.n_invalid == 7 and rep.n_valid == 3
    r = rep.invalid_reasons()
    assert "wrong length 63" in r[1] and "wrong length 8" in r[2] and "wrong length 0" in r[3]
    assert "duty_b" in r[4] and "i_c" in r[5] and "vdc" in r[6] and "v_ab" in r[7]
    assert np.all(np.isnan(frames[1:4]))
    assert np.array_equal(frames[[0, 8, 9]], cp.fd_payloads_to_frames(pay[[0, 8, 9]]))
    # arbitrary garbage never raises
    rng = np.random.default_rng(3)
    junk = [rng.integers(0, 256, rng.integers(0, 70), dtype=np.uint8).tobytes()
            for _ in range(200)]  # fmt: skip
    _, res2 = proto.decode_fd(junk)
    assert res2.report.valid.shape == (200,)
    assert all(res2.report.reasons[i] for i in np.flatnonzero(~res2.report.valid))


def test_nan_and_out_of_range_values_rejected_before_encoding(proto):
    f = make_frames(6)
    f[1, FD["i_a"]] = np.nan
    f[2, FD["v_bc"]] = np.inf
    f[3, FD["duty_c"]] = 1.5
    f[4, FD["vdc"]] = -3.0
    vals = proto.frames_to_signal_values(f)
    rep = proto.fd_codec.validate_values(vals)
    assert rep.valid.tolist() == [True, False, False, False, False, True]
    assert "i_a is nan" in rep.reasons[1] and "v_bc is inf" in rep.reasons[2]
    assert "duty_c=1.5 outside [0, 1]" in rep.reasons[3] and "vdc" in rep.reasons[4]
    with pytest.raises(ValueError, match="invalid rows"):
        cp.frames_to_fd_payloads(f)
    with pytest.raises(ValueError):
        cp.frame_to_fd_payload(f[1])
    nan_seq = make_frames(1)
    nan_seq[0, FD["seq"]] = np.nan
    with pytest.raises(ValueError):
        cp.frame_to_fd_payload(nan_seq[0])


# --------------------------------------------------------------------------- seq


def test_seq_gap_counting_with_wrap():
    seq = [65530, 65531, 65533, 65534, 65535, 0, 1, 1, 5, 6, 3, 4]
    st = cp.count_seq_gaps(seq)
    assert st.frames == 12
    assert st.gaps == 2 and st.lost == 1 + 3  # 65532 and 2, 3, 4
    assert st.duplicates == 1 and st.out_of_order == 1
    assert st.last == 4
    # continuous stream across the wrap: no gaps
    cont = np.arange(60_000, 70_000) % 65536
    assert cp.count_seq_gaps(cont).gaps == 0
    # streaming == batch, including across chunk boundaries
    tr = cp.SeqTracker()
    for s in seq[:5]:
        tr.update(s)
    tr.update_many(seq[5:])
    assert tr.stats.as_dict() == {**st.as_dict(), "frames": 12}
    assert cp.SeqTracker().update(3) == 0
    # classic layout: seq advances by D
    d = 8
    cl = (np.arange(0, 8 * 100, d) + 65000) % 65536
    assert cp.count_seq_gaps(cl, step=d).gaps == 0
    st2 = cp.count_seq_gaps(np.delete(cl, [10, 11, 50]), step=d)
    assert st2.gaps == 2 and st2.lost == 3


def test_unwrap_counter():
    true = np.cumsum(np.full(200, 100_000.0)) - 9_000_000
    wrapped = (true + 2**23) % 2**24 - 2**23
    un = cp.unwrap_counter(wrapped, 24)
    assert np.array_equal(un - un[0], true - true[0])
    un2 = cp.unwrap_counter(wrapped[100:], 24, prev=true[99])
    assert np.array_equal(un2, true[100:])


# --------------------------------------------------------------------------- classic


def test_classic_multiframe_reassembly(proto):
    rng = np.random.default_rng(11)
    n = 8 * 60 + 1
    f = make_frames(n, seed=5)
    f[:, FD["seq"]] = np.arange(n) + 65_000
    f[:, FD["encoder_counts"]] = 8_000_000 + np.cumsum(rng.integers(0, 40_000, n))
    f[:, FD["pwm_enabled"]] = 1
    dec = cp.decimate_for_classic(f, 8)
    assert dec.shape == (60, 14)
    assert np.allclose(dec[0, FD["v_ab"]], f[1:9, FD["v_ab"]].mean())
    assert dec[0, FD["seq"]] == f[8, FD["seq"]] and dec[0, FD["i_a"]] == f[8, FD["i_a"]]
    stream: list[tuple[int, bytes]] = []
    for row in dec:
        parts = cp.frame_to_classic_payloads(row)
        assert [p[0] for p in parts] == list(cp.CLASSIC_SAMPLE_IDS)
        assert all(len(p[1]) == 8 for p in parts)
        stream.extend(parts)
    # drop one part of sample 7, corrupt one part of sample 20, add foreign traffic
    del stream[7 * 4 + 2]
    stream[20 * 4 - 1 + 1] = (stream[20 * 4][0], stream[20 * 4][1][:5])
    stream.insert(3, (cp.ID_STATUS, bytes(8)))
    ra = cp.ClassicReassembler(protocol=proto)
    out = ra.feed_many(stream)
    assert ra.completed == 58 and ra.incomplete == 2 and ra.malformed == 1
    assert "wrong length 5" in ra.reasons[0]
    keep = np.array([i for i in range(60) if i not in (7, 20)])
    ref = dec[keep]
    assert np.max(np.abs(out[:, CUR] - ref[:, CUR])) <= 0.0005 + 1e-12
    assert np.max(np.abs(out[:, VLL] - ref[:, VLL])) <= 0.002 + 1e-12
    assert np.max(np.abs(out[:, DUTY] - ref[:, DUTY])) <= 1e-5 + 1e-12
    # the 24-bit encoder is unwrapped back to the full count
    assert np.array_equal(out[:, FD["encoder_counts"]], ref[:, FD["encoder_counts"]])
    assert np.array_equal(out[:, FD["seq"]], np.mod(ref[:, FD["seq"]], 65536))
    st = cp.count_seq_gaps(out[:, FD["seq"]], step=8)
    assert st.gaps == 2 and st.lost == 2


# --------------------------------------------------------------------------- commands


def test_command_frames_round_trip(proto):
    duty = proto.encode("DUTY_CMD", {"cmd_seq": 65535, "cmd_duty_a": 1.0, "cmd_duty_b": 0.0,
                                     "cmd_duty_c": 0.33333, "cmd_enable": 1})  # fmt: skip
    assert len(duty) == 8
    d = proto.decode(cp.ID_DUTY_CMD, duty)
    assert d["cmd_seq"] == 65535 and d["cmd_enable"] == 1
    assert d["cmd_duty_a"] == pytest.approx(1.0) and d["cmd_duty_c"] == pytest.approx(0.33332)
    arm = proto.encode("ARM_MODE", {"arm": 1, "arm_key": cp.ARM_KEY, "mode": 1,
                                    "cmd_timeout": 0.001, "decimation": 8})  # fmt: skip
    a = proto.decode("ARM_MODE", arm, decode_choices=True)
    assert a["arm"] == 1 and a["arm_key"] == 0xA5 and str(a["mode"]) == "RUN"
    assert a["cmd_timeout"] == pytest.approx(0.001)
    flt = proto.encode("FAULT", {"fault_code": 1, "fault_latched": 1, "fault_detail": 1234,
                                 "fault_seq": 42})  # fmt: skip
    fd = proto.decode(cp.ID_FAULT, flt, decode_choices=True)
    assert str(fd["fault_code"]) == "OVERCURRENT" and fd["fault_latched"] == 1
    st = proto.decode("STATUS", proto.encode("STATUS", {"st_state": 3, "st_temp": -5,
                                                        "st_protocol_version": 1,
                                                        "st_decimation": 8}))  # fmt: skip
    assert st["st_state"] == 3 and st["st_temp"] == -5
    with pytest.raises(Exception):  # noqa: B017 - cantools raises EncodeError (strict)
        proto.encode("DUTY_CMD", {"cmd_duty_a": 1.2, "cmd_seq": 1})


def test_frame_layout_matches_plant():
    """FRAME_FIELDS must mirror the engine's FR_* column indices (when importable)."""
    plant = pytest.importorskip("fluxdrive.drive.plant")
    names = {
        "FR_IA": "i_a", "FR_IB": "i_b", "FR_IC": "i_c", "FR_VAB": "v_ab", "FR_VBC": "v_bc",
        "FR_VCA": "v_ca", "FR_VDC": "vdc", "FR_DA": "duty_a", "FR_DB": "duty_b",
        "FR_DC": "duty_c", "FR_EN": "pwm_enabled", "FR_ENC": "encoder_counts",
        "FR_SEQ": "seq", "FR_FLAGS": "flags",
    }  # fmt: skip
    assert plant.FR_N == len(cp.FRAME_FIELDS)
    for fr, name in names.items():
        assert getattr(plant, fr) == cp.FRAME_INDEX[name], fr


# --------------------------------------------------------------------------- bus time


def test_frame_bits_and_link_budget():
    # classic base frame, 8 bytes: 111 bits, 135 with worst-case stuffing (Davis et al.)
    assert cp.frame_bits(8) == (111, 0) and cp.frame_bits(8, stuffing="worst") == (135, 0)
    assert cp.frame_bits(0) == (47, 0) and cp.frame_bits(2) == (63, 0)
    # CAN FD, 64 bytes with BRS: 29 bits at the nominal rate, 550 at the data rate
    assert cp.frame_bits(64, fd=True, brs=True) == (29, 550)
    assert cp.frame_bits(38, fd=True, brs=True) == cp.frame_bits(48, fd=True, brs=True)
    assert cp.frame_bits(64, fd=True) == (579, 0)
    assert cp.bus_time_s(64, 1e6, 5e6, fd=True, brs=True) == pytest.approx(139e-6)
    with pytest.raises(ValueError):
        cp.frame_bits(9)
    # classic at 10 kHz: 4 sample parts + the duty = 555..675 bits every 100 us
    full = cp.link_budget("classic", decimation=1)
    assert full["bits_none"]["nominal"] == 555 and full["bits_worst"]["nominal"] == 675
    assert not full["fits"] and full["load_none"] > 5.5
    assert not cp.link_budget("classic", decimation=6)["fits"]  # worst case 113 %
    d8 = cp.link_budget("classic", decimation=8)
    assert d8["fits"] and 0.69 < d8["load_none"] < 0.70 and 0.84 < d8["load_worst"] < 0.85
    assert d8["host_budget_us_worst"] == pytest.approx(125.0)
    # the FD layout at 10 kHz and 1/5 Mbit/s: the 64-byte sample alone takes 139 us
    fd = cp.link_budget("fd")
    assert not fd["fits"] and fd["bus_time_us_none"] == pytest.approx(250.0)
    # decimated FD: D = 2 and 3 still do not fit 1/5 Mbit/s (152 %, 102 % worst case),
    # D = 4 does (63-76 %, 96-150 us for the host), the DBC's FdDecimationRealBus; 1/8: D = 3
    assert not cp.link_budget("fd", decimation=2)["fits"]
    assert not cp.link_budget("fd", decimation=3)["fits"]
    fd4 = cp.link_budget("fd", decimation=4)
    assert fd4["fits"] and fd4["bus_time_us_none"] == pytest.approx(250.0)
    assert 0.62 < fd4["load_none"] < 0.63 and 0.76 < fd4["load_worst"] < 0.77
    assert fd4["host_budget_us_none"] == pytest.approx(150.0)
    assert 96.0 < fd4["host_budget_us_worst"] < 97.0
    proto = cp.get_protocol()
    assert cp.smallest_fitting_decimation("fd") == proto.fd_decimation_real_bus == 4
    assert cp.smallest_fitting_decimation("fd", data_bitrate=8e6) == 3
    assert cp.smallest_fitting_decimation("classic") == 7
    assert proto.default_decimation("fd") == proto.fd_decimation == 1
    assert proto.default_decimation("classic") == proto.classic_decimation == 8
    with pytest.raises(ValueError, match="fits no decimation"):
        cp.smallest_fitting_decimation("fd", nominal_bitrate=125e3, max_decimation=4)


def test_one_frame_codec_equals_vectorised(proto):
    rng = np.random.default_rng(8)
    for fid, codec in proto.classic_codecs.items():
        msg = proto.message(fid)
        raw = random_raw(msg, 200, rng)
        pay = codec.encode_raw(raw)
        rows = [r.tobytes() for r in pay] + [pay[0, :5].tobytes()]
        res = codec.decode_checked(rows)
        for i, row in enumerate(rows):
            vals, reason = codec.decode_one(row)
            assert reason == res.report.reasons[i]
            if res.report.valid[i]:
                assert np.array_equal(vals, res.values[i])
                assert codec.encode_one(dict(zip(codec.names, vals, strict=True))) == row
            else:
                assert vals is None and reason
        with pytest.raises(ValueError):
            codec.encode_one({codec.names[1]: float("nan")})
