"""CAN captures against the formats' specifications and a third reader.

- PCAN `.trc` (version 2.1, FD frame types) imports like the other formats (python-can reads
  it; the file here is laid out as PEAK's TRC 2.1 description gives it);
- the `.blf` and candump `.log` the project writes (fluxdrive.can.canlog) read back frame for
  frame through a reader written after SavvyCAN's handling of those formats (its BLF walk:
  144-byte file header, LOBJ objects, each log container inflated and walked on its own with
  a 4-byte signature scan at its start, objects of the version-1 header; its candump
  tokenisation), extended with what SavvyCAN does not read yet, by the specifications: the
  BLF CAN_FD_MESSAGE object (type 100; SavvyCAN declares its layout, BLF_CANFD_OBJ, but
  handles types 1 and 86 only) and can-utils' FD line `<id>##<flags><data>` (SavvyCAN's
  `(\\S+)#(\\S+)` pattern would read `123#` as the id and the flags nibble as data).
"""

from __future__ import annotations

import re
import struct
import zlib
from datetime import UTC, datetime
from pathlib import Path

import can
import numpy as np
import pytest
from fluxdrive.can import canlog
from fluxdrive.can import protocol as cp
from fluxdrive.drive.plant import FR_DA, FR_DC, FR_IA, FR_IC, FR_VAB, FR_VCA, FR_VDC

FD = cp.FRAME_INDEX
BLF_CAN_MSG, BLF_CAN_MSG2, BLF_CONTAINER, BLF_CAN_FD_MSG = 1, 86, 10, 100


def _frames(n: int, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.zeros((n, len(cp.FRAME_FIELDS)))
    f[:, FR_IA : FR_IC + 1] = rng.uniform(-20, 20, (n, 3))
    f[:, FR_VAB : FR_VCA + 1] = rng.uniform(-72, 72, (n, 3))
    f[:, FR_VDC] = rng.uniform(60, 80, n)
    f[:, FR_DA : FR_DC + 1] = rng.uniform(0, 1, (n, 3))
    f[:, FD["encoder_counts"]] = rng.integers(-(2**31), 2**31, n)
    f[:, FD["pwm_enabled"]] = 1
    f[:, FD["seq"]] = np.arange(n) % 65536
    return f


# --------------------------------------------------- a reader after SavvyCAN's handling
def savvy_blf(path: Path) -> list[dict]:
    """BLF frames the way SavvyCAN's BLFHandler::loadBLF walks a file, plus CAN FD objects."""
    raw = path.read_bytes()
    assert raw[:4] == b"LOGG", "file signature"
    pos = 144  # SavvyCAN reads sizeof(BLF_FILE_HEADER) = 144 bytes, whatever headerSize says
    out: list[dict] = []
    pending = b""  # uncompressed bytes not consumed by the last container's walk
    while pos < len(raw):
        sig, _hsize, _hver, obj_size, obj_type = struct.unpack_from("<4sHHII", raw, pos)
        assert sig == b"LOBJ", f"object signature at {pos}"
        read_size = obj_size - 16
        body = raw[pos + 16 : pos + 16 + read_size]
        pos += 16 + read_size + read_size % 4  # its padding rule
        if obj_type != BLF_CONTAINER:
            continue
        method = struct.unpack_from("<H", body, 0)[0]
        payload = body[16:]
        buf = pending + (zlib.decompress(payload) if method == 2 else payload)
        p = 0
        while p + 40 < len(buf):  # first skip forward to an object signature
            if buf[p : p + 4] == b"LOBJ":
                break
            p += 4
        while p + 40 < len(buf):  # sizeof(BLF_OBJ_HEADER): base 16 + the union's 24
            _sig, _hs, _hv, size, otype = struct.unpack_from("<4sHHII", buf, p)
            _flags, _client, _ver, stamp = struct.unpack_from("<IHHQ", buf, p + 16)
            data = buf[p + 32 : p + size]  # QByteArray::mid: cut short at the end
            if otype in (BLF_CAN_MSG, BLF_CAN_MSG2):
                ch, flags, dlc, aid = struct.unpack_from("<HBBI", data, 0)
                out.append(
                    {
                        "bus": ch,
                        "id": aid & 0x1FFFFFFF,
                        "ext": bool(aid & 0x80000000),
                        "fd": False,
                        "data": bytes(data[8 : 8 + dlc]),
                        "t_ns": stamp,
                    }
                )
            elif otype == BLF_CAN_FD_MSG and len(data) >= 84:  # BLF_CANFD_OBJ
                ch, flags, dlc, aid, _flen, _bits, fd_flags, valid = struct.unpack_from(
                    "<HBBIIBBB", data, 0
                )
                out.append(
                    {
                        "bus": ch,
                        "id": aid & 0x1FFFFFFF,
                        "ext": bool(aid & 0x80000000),
                        "fd": bool(fd_flags & 1),
                        "brs": bool(fd_flags & 2),
                        "data": bytes(data[20 : 20 + valid]),
                        "t_ns": stamp,
                    }
                )
            p += size + size % 4
        pending = buf[p:] if p < len(buf) else b""  # uncompressedData.remove(0, pos)
    return out


def savvy_candump(path: Path) -> list[dict]:
    """candump .log lines the way SavvyCAN's loadCanDumpFile tokenises them (concise
    format), with can-utils' FD syntax `<id>##<flags><data>` read by its definition."""
    out = []
    for line in path.read_text().upper().splitlines():
        tokens = line.split()
        if len(tokens) < 3:
            continue
        m = re.fullmatch(r"\((\S+)\)", tokens[0])
        if not m:
            continue
        bus = int(re.search(r"\d+", tokens[1]).group()) if re.search(r"\d", tokens[1]) else 0
        if "##" in tokens[2]:
            ident, rest = tokens[2].split("##", 1)
            flags, hexdata, fd = int(rest[0], 16), rest[1:].replace(".", ""), True
        else:
            m2 = re.fullmatch(r"(\S+)#(\S+)", tokens[2])
            if not m2:
                continue
            ident, hexdata, flags, fd = m2.group(1), m2.group(2), 0, False
        out.append(
            {
                "bus": bus,
                "id": int(ident, 16),
                "ext": len(ident) > 3,
                "fd": fd,
                "brs": bool(flags & 1),
                "data": bytes.fromhex(hexdata),
                "t_us": int(round(float(m.group(1)) * 1e6)),
            }
        )
    return out


@pytest.mark.parametrize("suffix", [".blf", ".log"])
def test_written_captures_read_back_through_a_savvycan_style_reader(tmp_path, suffix):
    n = 2500  # .blf: ~300 kB of objects, three log containers
    pay = cp.frames_to_fd_payloads(_frames(n))
    ts = 1_700_000_000.0 + 1e-4 * np.arange(n)
    path = tmp_path / f"capture{suffix}"
    canlog.write_capture(path, pay, timestamps=ts)
    got = savvy_blf(path) if suffix == ".blf" else savvy_candump(path)
    assert len(got) == n
    assert all(g["fd"] and g["brs"] and not g["ext"] for g in got)
    assert all(g["id"] == cp.ID_SAMPLE_FD for g in got)
    assert [g["data"] for g in got] == [r.tobytes() for r in pay]
    if suffix == ".blf":
        t = np.array([g["t_ns"] for g in got]) * 1e-9
        assert np.allclose(t - t[0], ts - ts[0], atol=1e-9)
    else:
        t = np.array([g["t_us"] for g in got]) * 1e-6
        assert np.allclose(t, ts, atol=1e-6)
    # and python-can's reader (the importer) agrees
    res = canlog.read_capture(path)
    assert res.counts["decoded"] == n and res.counts["malformed"] == 0


def test_blf_fd_objects_have_the_size_the_format_defines(tmp_path):
    """CAN_FD_MESSAGE: 32-byte object header + 88 bytes (channel .. 64 data bytes and the
    trailing reserved DWORD): 120; every log container holds whole objects."""
    n = 2500
    pay = cp.frames_to_fd_payloads(_frames(n, seed=4))
    path = tmp_path / "c.blf"
    canlog.write_capture(path, pay)
    raw = path.read_bytes()
    pos, sizes, containers = 144, set(), 0
    while pos < len(raw):
        _sig, _h, _v, obj_size, obj_type = struct.unpack_from("<4sHHII", raw, pos)
        assert obj_type == BLF_CONTAINER
        method = struct.unpack_from("<H", raw, pos + 16)[0]
        body = raw[pos + 32 : pos + obj_size]
        pos += obj_size + obj_size % 4
        containers += 1
        buf = zlib.decompress(body) if method == 2 else body
        p = 0
        while p < len(buf):
            size, otype = struct.unpack_from("<II", buf, p + 8)
            assert buf[p : p + 4] == b"LOBJ" and p + size <= len(buf), "an object cut"
            sizes.add((otype, size))
            p += size + size % 4
    assert sizes == {(BLF_CAN_FD_MSG, 120)}
    assert containers >= 2
    # python-can's own writer cuts objects across containers: SavvyCAN's walk loses them
    plain = tmp_path / "plain.blf"
    with can.Logger(str(plain)) as w:
        for r in pay:
            w.on_message_received(
                can.Message(arbitration_id=cp.ID_SAMPLE_FD, is_fd=True, data=r.tobytes(), channel=1)
            )
    assert len(savvy_blf(plain)) < n == len(savvy_blf(path))


def _trc_v21(path: Path, pay: np.ndarray, t0: datetime, period_s: float) -> None:
    """A PCAN-View trace, file version 2.1 (PEAK's TRC format description): header lines
    with the start time as days since 1899-12-30 and the column list, then one line per
    frame: number, offset [ms], type (FB: CAN FD with bit rate switch), bus, id, direction,
    reserved, DLC code, data bytes."""
    days = (t0 - datetime(1899, 12, 30, tzinfo=UTC)).total_seconds() / 86400.0
    lines = [
        ";$FILEVERSION=2.1",
        f";$STARTTIME={days:.10f}",
        ";$COLUMNS=N,O,T,B,I,d,R,L,D",
        ";",
        ";   Message   Time    Type ID     Rx/Tx",
        ";   Number    Offset  |    Bus    [hex]  |  Reserved",
        ";   |         [ms]    |    |      |      |  |  Data Length Code",
        ";   |         |       |    |      |      |  |  |    Data [hex] ...",
    ]
    for i, r in enumerate(pay):
        data = " ".join(f"{b:02X}" for b in r.tobytes())
        lines.append(
            f"{i + 1:>7} {i * period_s * 1e3:13.3f} FB {1:>2} {cp.ID_SAMPLE_FD:04X}"
            f" Rx - {15:>2}    {data}"
        )
    path.write_text("\n".join(lines) + "\n")


def test_trc_capture_imports(tmp_path):
    n = 400
    f = _frames(n, seed=5)
    pay = cp.frames_to_fd_payloads(f)
    path = tmp_path / "pcan.trc"
    t0 = datetime(2026, 11, 25, 12, 0, 0, tzinfo=UTC)
    _trc_v21(path, pay, t0, 1e-4)
    res = canlog.read_capture(path)
    assert res.layout == "fd"
    assert res.counts["total"] == n and res.counts["decoded"] == n
    assert res.counts["malformed"] == 0 and res.counts["gaps"] == 0
    assert np.array_equal(res.frames, cp.fd_payloads_to_frames(pay))
    assert np.allclose(res.timestamps - t0.timestamp(), 1e-4 * np.arange(n), atol=2e-6)
    # a damaged line is skipped and named; the rest imports
    text = path.read_text().splitlines()
    text[20] = text[20][:-5] + "ZZ QQ"  # frame 13: data bytes that are not hex
    bad = tmp_path / "bad.trc"
    bad.write_text("\n".join(text) + "\n")
    res = canlog.read_capture(bad)
    assert res.counts["malformed_lines"] + res.counts.get("malformed", 0) >= 1
    assert res.counts["decoded"] == n - 1


def test_trc_is_read_not_written(tmp_path):
    with pytest.raises(ValueError, match="drops CAN FD"):
        canlog.write_capture(tmp_path / "x.trc", [bytes(64)])
    with pytest.raises(ValueError, match="unsupported capture format"):
        canlog.read_capture(tmp_path / "x.pcap")
