"""The C drive firmware (firmware/) on this machine: its C unit tests, its DBC codec against
cantools, its protections and current loop against the engine, and the software-in-the-loop
drive (DriveEmulator: the plant and the C core) against the plant's own frames. No ROS."""

from __future__ import annotations

import ctypes
import math
import re
import subprocess

import can
import numpy as np
import pytest
from fluxdrive.can import firmware as fw
from fluxdrive.can.protocol import (
    ARM_KEY,
    CLASSIC_SAMPLE_IDS,
    ID_SAMPLE_FD,
    ID_STATUS,
    load_database,
)
from fluxdrive.drive import control as ctl
from fluxdrive.drive import plant as pl
from fluxdrive.drive.control import kernel

U8_64 = ctypes.c_uint8 * 64


@pytest.fixture(scope="module")
def lib():
    return fw.load_library()


@pytest.fixture(scope="module")
def db():
    return load_database()


def test_c_unit_tests_pass_and_core_uses_no_heap(lib):
    bdir = fw.host_build_dir()
    r = subprocess.run(
        ["ctest", "--test-dir", str(bdir), "--output-on-failure"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    print(r.stdout[-2000:])
    assert r.returncode == 0, r.stdout + r.stderr
    undefined = subprocess.run(
        ["nm", "-u", str(bdir / "libfdcore.a")], capture_output=True, text=True, check=True
    ).stdout.split()
    assert not {"malloc", "calloc", "realloc", "free"} & set(undefined)


def _on_grid(rng, lo, hi, scale, n, spread=0.4):
    """n float32 values in [lo, hi] at least 0.1 LSB away from a rounding boundary: a value
    within float32 rounding of x.5 LSB could round either way in float32 and float64.
    ``spread`` (LSB) 0.1 keeps values on a grid 4x coarser than the finest field they go to
    0.1 of that field's LSB away from its boundaries too."""
    raw = rng.integers(round(lo / scale), round(hi / scale), n, endpoint=True)
    return (raw + rng.uniform(-spread, spread, n)).clip(lo / scale, hi / scale) * scale


SINCOS_ERR_MAX = float(
    re.search(
        r"#define FD_SINCOS_ERR_MAX ([0-9.e+-]+)f",
        (fw.FIRMWARE_DIR / "include" / "fd_math.h").read_text(),
    ).group(1)  # type: ignore[union-attr]
)
"""fd_sincosf's absolute error bound (firmware/include/fd_math.h)."""


def _f32(x):
    return float(np.float32(x))


def test_encoders_are_cantools_byte_for_byte(lib, db):
    """Every message the core sends, over many seeded random in-range values."""
    rng = np.random.default_rng(20261125)
    buf = U8_64()
    n = 400
    fault = db.get_message_by_name("FAULT")
    status = db.get_message_by_name("STATUS")
    ack = db.get_message_by_name("DRIVE_PARAM_ACK")
    sfd = db.get_message_by_name("SAMPLE_FD")
    classic = [db.get_message_by_name(f"SAMPLE_C_{p}") for p in ("CUR", "VLT", "DUTY", "AUX")]
    for _ in range(n):
        v = {
            "fault_code": int(rng.choice([0, 1, 2, 3, 4, 9, 16, 20])),
            "fault_latched": int(rng.integers(2)),
            "fault_active": int(rng.integers(2)),
            "fault_pwm_disabled": int(rng.integers(2)),
            "fault_detail": int(rng.integers(65536)),
            "fault_seq": int(rng.integers(65536)),
            "fault_count": int(rng.integers(256)),
        }
        ln = lib.fd_encode_fault(buf, *v.values())
        assert bytes(buf[:ln]) == fault.encode(v)

        v = {
            "st_alive": int(rng.integers(256)),
            "st_state": int(rng.integers(5)),
            "st_armed": int(rng.integers(2)),
            "st_pwm_enabled": int(rng.integers(2)),
            "st_fault_latched": int(rng.integers(2)),
            "st_sample_layout": int(rng.integers(2)),
            "st_decimation": int(rng.integers(1, 256)),
            "st_tx_overruns": int(rng.integers(65536)),
            "st_temp": int(rng.integers(-128, 128)),
            "st_rx_errors": 0,
        }
        args = list(v.values())
        ln = lib.fd_encode_status(buf, *args)
        assert bytes(buf[:ln]) == status.encode({**v, "st_protocol_version": 2})

        pv = _f32(rng.normal() * 10.0 ** rng.integers(-6, 6))
        v = {
            "pa_id": int(rng.integers(1, 17)),
            "pa_seq": int(rng.integers(256)),
            "pa_status": int(rng.integers(6)),
            "pa_value": pv,
        }
        ln = lib.fd_encode_param_ack(buf, *v.values())
        assert bytes(buf[:ln]) == ack.encode(v)

        f = np.concatenate(
            [
                _on_grid(rng, -25.0, 25.0, 0.001, 3),
                _on_grid(rng, -100.0, 100.0, 0.004, 3, 0.1),  # the 1 mV and the 4 mV grid
                _on_grid(rng, 0.0, 100.0, 0.002, 1),
                _on_grid(rng, 0.0, 1.0, 2e-5, 3),
            ]
        ).astype(np.float32)
        fp = f.ctypes.data_as(ctypes.POINTER(ctypes.c_float))
        enc = int(rng.integers(-(2**31), 2**31))
        flags = int(rng.integers(128))
        seq, applied = int(rng.integers(65536)), int(rng.integers(65536))
        t_us, mode, code = int(rng.integers(2**32 - 1)), int(rng.integers(3)), 9
        ln = lib.fd_encode_sample_fd(buf, seq, fp, enc, applied, t_us, flags, mode, code)
        x = [float(a) for a in f]
        bit = [(flags >> b) & 1 for b in range(7)]
        want = sfd.encode(
            {
                "seq": seq, "i_a": x[0], "i_b": x[1], "i_c": x[2], "v_ab": x[3],
                "v_bc": x[4], "v_ca": x[5], "vdc": x[6], "duty_a": x[7], "duty_b": x[8],
                "duty_c": x[9], "encoder": enc, "cmd_seq_applied": applied,
                "t_mcu": t_us * 1e-6, "pwm_enabled": bit[0], "armed": bit[1],
                "fault_active": bit[2], "adc_clip": bit[3], "cmd_stale": bit[4],
                "capture_valid": bit[5], "control_split": bit[6], "mode": mode,
                "fault_code": code,
            }
        )  # fmt: skip
        assert ln == 64 and bytes(buf[:64]) == want

        out = (ctypes.c_uint8 * 32)()
        assert lib.fd_encode_sample_classic(out, seq, fp, enc, flags) == 32
        enc24 = (enc + 2**23) % 2**24 - 2**23
        want4 = [
            classic[0].encode({"c_seq": seq, "c_i_a": x[0], "c_i_b": x[1], "c_i_c": x[2]}),
            classic[1].encode({"c_seq": seq, "c_v_ab": x[3], "c_v_bc": x[4], "c_v_ca": x[5]}),
            classic[2].encode(
                {"c_seq": seq, "c_duty_a": x[7], "c_duty_b": x[8], "c_duty_c": x[9]}
            ),
            classic[3].encode(
                {
                    "c_seq": seq, "c_vdc": x[6], "c_encoder": enc24, "c_pwm_enabled": bit[0],
                    "c_armed": bit[1], "c_fault_active": bit[2], "c_adc_clip": bit[3],
                    "c_cmd_stale": bit[4], "c_capture_valid": bit[5], "c_control_split": bit[6],
                }
            ),
        ]  # fmt: skip
        assert bytes(out) == b"".join(want4)


def test_host_frames_decode_like_cantools(lib, db):
    """What the host sends, decoded by the generated codec = cantools' decoding."""
    rng = np.random.default_rng(7)
    out = (ctypes.c_float * 10)()
    names = ("ARM_MODE", "DUTY_CMD", "HOST_REF", "DRIVE_PARAM", "HOST_HEARTBEAT")
    for name in names:
        msg = db.get_message_by_name(name)
        for _ in range(200):
            vals = {}
            for s in msg.signals:
                if s.is_float:
                    vals[s.name] = _f32(rng.normal() * 10.0 ** rng.integers(-4, 5))
                    continue
                lo = int(round(((s.minimum or 0.0) - s.offset) / s.scale))
                hi = int(round(((s.maximum or 0.0) - s.offset) / s.scale))
                vals[s.name] = int(rng.integers(lo, hi, endpoint=True)) * s.scale + s.offset
            data = msg.encode(vals)
            n = lib.fd_sil_decode_host(msg.frame_id, (ctypes.c_uint8 * len(data))(*data),
                                       len(data), out)  # fmt: skip
            assert n == len(msg.signals)
            ref = msg.decode(data, decode_choices=False, scaling=True)
            for j, s in enumerate(msg.signals):
                # C decodes raw * scale in float32
                assert out[j] == pytest.approx(float(ref[s.name]), rel=2e-7, abs=1e-30), s.name


def test_param_ids_are_the_dbc_table(lib, db):
    table = db.get_message_by_name("DRIVE_PARAM").get_signal_by_name("prm_id").choices
    assert {str(v): int(k) for k, v in table.items()} == fw.PARAM_IDS


# ---------------------------------------------------------------- engine reference values


def _card_mp():
    from fluxdrive.core.machine import MachineCard

    card = MachineCard()
    return card, pl.machine_params(card)


class _Drive:
    """A C core armed in host mode (D = 1), answering every sample with PWM on; samples
    built from SI values quantised like the plant's sensors."""

    def __init__(self, mp, cp):
        self.core = fw.FirmwareCore(mp)
        self.mp = mp
        for name, idx in (
            ("OVERCURRENT_A", ctl.CP_OC_TRIP),
            ("RATED_CURRENT_A", ctl.CP_IRATED),
            ("I2T_LIMIT_PU2S", ctl.CP_I2T_LIMIT),
            ("VDC_MIN_V", ctl.CP_VDC_MIN),
            ("VDC_MAX_V", ctl.CP_VDC_MAX),
        ):
            assert self.core.param_write(name, float(cp[idx])) == "OK"
        self.frame = np.zeros(pl.FR_N)
        self.db = load_database()
        self.arm = self.db.get_message_by_name("ARM_MODE")
        self.duty = self.db.get_message_by_name("DUTY_CMD")
        self.core.push(self._arm_msg())

    def _arm_msg(self):
        data = self.arm.encode(
            {"arm": 1, "arm_key": ARM_KEY, "reset_fault": 0, "sample_layout": 0,
             "control_split": 0, "mode": 1, "cmd_timeout": 0, "decimation": 1,
             "arm_counter": 0}
        )  # fmt: skip
        return can.Message(arbitration_id=self.arm.frame_id, data=data, is_extended_id=False)

    def sample(self, i_abc, vdc):
        """One period on these readings; returns the core's fault code."""
        k = self.core.k
        if k >= 1:
            data = self.duty.encode(
                {"cmd_seq": k - 1, "cmd_duty_a": 0.5, "cmd_duty_b": 0.5, "cmd_duty_c": 0.5,
                 "cmd_enable": 1}
            )  # fmt: skip
            self.core.push(
                can.Message(arbitration_id=self.duty.frame_id, data=data, is_extended_id=False)
            )
        self.frame[pl.FR_IA : pl.FR_IC + 1] = i_abc
        self.frame[pl.FR_VDC] = vdc
        self.core.set_sample(self.frame, k * 100)
        self.core.period()
        self.core.pop_tx()
        return self.core.state()["fault_code"]


def _quantise(x, lsb):
    return np.floor(np.asarray(x) / lsb + 0.5) * lsb


def _engine_protect(cs, cp, i_abc, vdc, ts):
    fr = np.zeros(pl.FR_N)
    fr[pl.FR_IA : pl.FR_IC + 1] = i_abc
    fr[pl.FR_VDC] = vdc
    out = np.zeros(ctl.CO_N)
    ia, ib = (2 * i_abc[0] - i_abc[1] - i_abc[2]) / 3.0, (i_abc[1] - i_abc[2]) / math.sqrt(3.0)
    kernel._protect(cs, cp, fr, out, ia, ib, ts)
    return int(cs[ctl.CS_FAULT]) if cs[ctl.CS_MODE] == ctl.MODE_FAULT else 0


@pytest.mark.parametrize("case", ["i2t", "overcurrent", "overvoltage", "undervoltage"])
def test_protections_trip_where_the_engine_trips(lib, case):
    """Same samples into the engine's _protect and into the C core (armed, PWM on): the
    same fault code at the same period; the I2t integral agrees to float32 rounding."""
    card, mp = _card_mp()
    cfg = ctl.ControllerConfig(i2t_limit_pu2s=0.05 if case == "i2t" else 10.0)
    cp = cfg.to_params(card)
    ts = card.ts_s
    irated = card.rated_current_a
    lsb = float(mp[pl.MP_ADC_LSB])
    vlsb = float(mp[pl.MP_VDC_LSB])
    n = 2000
    t = np.arange(n) * ts
    amp = np.full(n, 0.5 * irated)
    vdc = np.full(n, card.dc_bus_v)
    if case == "i2t":
        amp[100:] = 1.6 * irated  # 1.56 pu^2 over rated: trips after ~0.032 s
    elif case == "overcurrent":
        amp[300:] = np.linspace(1.9, 2.3, n - 300) * irated
    elif case == "overvoltage":
        vdc[200:] = np.linspace(card.dc_bus_v, 1.5 * card.dc_bus_v, n - 200)
    else:
        vdc[200:] = np.linspace(card.dc_bus_v, 0.1 * card.dc_bus_v, n - 200)
    th = 2 * np.pi * 5.0 * t
    i_abc = np.stack([amp * np.cos(th - j * 2 * np.pi / 3) for j in range(3)], axis=1)
    i_abc = _quantise(i_abc, lsb)
    vdc = _quantise(vdc, vlsb)
    cs = np.zeros(ctl.CS_N)
    cs[ctl.CS_MODE] = ctl.MODE_CLOSED_LOOP
    drive = _Drive(mp, cp)
    drive.sample(i_abc[0], vdc[0])  # period 0 arms; the engine starts with sample 1
    i2t_c = np.float32(0.0)
    trip_engine = trip_c = None
    for k in range(1, n):
        code_e = _engine_protect(cs, cp, i_abc[k], vdc[k], ts)
        code_c = drive.sample(i_abc[k], vdc[k])
        if trip_engine is None and code_e:
            trip_engine = (k, code_e)
        if trip_c is None and code_c:
            trip_c = (k, code_c)
        if trip_engine is None:
            ia = (2 * i_abc[k, 0] - i_abc[k, 1] - i_abc[k, 2]) / 3.0
            ib = (i_abc[k, 1] - i_abc[k, 2]) / math.sqrt(3.0)
            i2t_c = lib.fd_i2t_step(i2t_c, ia, ib, irated, ts)
            assert i2t_c == pytest.approx(cs[ctl.CS_I2T], rel=1e-4, abs=1e-6)
        if trip_engine and trip_c:
            break
    want = {"i2t": 2, "overcurrent": 1, "overvoltage": 3, "undervoltage": 4}[case]
    print(f"{case}: engine trips at {trip_engine}, C core at {trip_c}")
    assert trip_engine is not None and trip_engine[1] == want
    assert trip_c == trip_engine
    st = drive.core.state()
    assert st["fault_latched"] and not st["pwm_enabled"] and drive.core.pwm()[1] is False


def test_current_loop_is_the_engines_in_float32(lib):
    """fd_current_loop against _current_loops: 300 chained steps on seeded random inputs
    (integrators carried on both sides), hexagon limit and deadtime feed-forward included.

    Tolerances: float32 rounding (the constant terms) plus fd_sincosf's error bound
    FD_SINCOS_ERR_MAX = e (tests/test_firmware_math.py) carried through the loop: Park's
    i_d = i_alpha cos + i_beta sin is off by at most (|i_alpha| + |i_beta|) e, the PI output
    by kp times that, the inverse Park at the advanced angle by (|v_d| + |v_q|) e, a duty by
    that over Vdc; the integrators by (kp + ki Ts) times the current error."""
    rng = np.random.default_rng(3)
    card, _ = _card_mp()
    cp = ctl.ControllerConfig().to_params(card)
    cp[ctl.CP_TDCOMP] = 1.0e-6
    ts = card.ts_s
    p = fw.CurParams(
        cp[ctl.CP_KP_I], cp[ctl.CP_KI_I], cp[ctl.CP_L], cp[ctl.CP_LAM],
        cp[ctl.CP_DECOUPLE], cp[ctl.CP_ADV], cp[ctl.CP_TDCOMP],
    )  # fmt: skip
    cs = np.zeros(ctl.CS_N)
    st = fw.CurState(0.0, 0.0)
    out = np.zeros(ctl.CO_N)
    o = fw.CurOut()
    saturated = 0
    for _k in range(300):
        ia, ib = rng.normal(0, 3, 2)
        th = rng.uniform(-np.pi, np.pi)
        we = rng.normal(0, 300)
        idr, iqr = rng.normal(0, 2), rng.normal(0, 6)
        vdc = card.dc_bus_v * rng.uniform(0.9, 1.1)
        args = [_f32(a) for a in (ia, ib, th, we, idr, iqr, vdc)]
        kernel._current_loops(cs, cp, *args[:6], args[6], ts, out)
        lib.fd_current_loop(ctypes.byref(st), ctypes.byref(p), *args, ts, ctypes.byref(o))
        vmag = math.hypot(out[ctl.CO_VD], out[ctl.CO_VQ])
        saturated += vmag > 0.5 * args[6]
        e_i = (abs(ia) + abs(ib)) * SINCOS_ERR_MAX  # Park's error from fd_sincosf
        e_v = abs(p.kp) * e_i + (abs(out[ctl.CO_VD]) + abs(out[ctl.CO_VQ])) * SINCOS_ERR_MAX
        tol_i = 1e-5 + e_i
        tol_v = 2e-5 * card.dc_bus_v + e_v
        tol_int = tol_v + (abs(p.kp) + abs(p.ki) * ts) * e_i
        np.testing.assert_allclose(
            list(o.duty), out[ctl.CO_DA : ctl.CO_DC + 1], atol=2e-6 + e_v / args[6]
        )
        assert o.i_d == pytest.approx(out[ctl.CO_ID], abs=tol_i)
        assert o.i_q == pytest.approx(out[ctl.CO_IQ], abs=tol_i)
        assert o.v_d == pytest.approx(out[ctl.CO_VD], abs=tol_v)
        assert o.v_q == pytest.approx(out[ctl.CO_VQ], abs=tol_v)
        assert st.id_i == pytest.approx(cs[ctl.CS_ID_I], abs=tol_int)
        assert st.iq_i == pytest.approx(cs[ctl.CS_IQ_I], abs=tol_int)
    assert saturated > 10  # the hexagon limit and the back-calculation were exercised


# ---------------------------------------------------------------- Cortex-M4F target


def test_cross_compiles_for_cortex_m4f_and_fits_the_g474():
    """The core cross-compiled with arm-none-eabi-gcc (hard float, -O2, -Werror) into the
    STM32G474 image; it fits the part's flash and SRAM, and no double-precision helper
    (soft-float __aeabi_d*) is linked: the float32 path stays on the FPU."""
    from fluxdrive.can import firmware_target as ft

    missing = ft.target_available()
    if missing:
        # the cross-compile is part of the test command: a missing toolchain is a failure
        pytest.fail(f"no ARM toolchain ({missing}); tools/bootstrap.sh installs it")
    bdir = ft.build_target()
    size = ft.target_sizes(bdir / "fd_g474.elf")
    print(f"STM32G474 image: flash {size['flash']} B, RAM {size['ram']} B")
    assert size["flash"] < 512 * 1024 and size["ram"] < 96 * 1024
    syms = subprocess.run(
        ["arm-none-eabi-nm", str(bdir / "fd_g474.elf")], capture_output=True, text=True, check=True
    ).stdout
    assert "__aeabi_dadd" not in syms and "__aeabi_dmul" not in syms
    assert " malloc" not in syms


# ---------------------------------------------------------------- software in the loop


def _arm_msg(db, layout="fd", decimation=1):
    arm_msg = db.get_message_by_name("ARM_MODE")
    return can.Message(
        arbitration_id=arm_msg.frame_id,
        is_extended_id=False,
        data=arm_msg.encode(
            {"arm": 1, "arm_key": ARM_KEY, "reset_fault": 0, "control_split": 0, "mode": 1,
             "sample_layout": int(layout == "classic"), "cmd_timeout": 0,
             "decimation": decimation, "arm_counter": 0}
        ),
    )  # fmt: skip


def _turning_duties(db, sc, n, d):
    """DUTY_CMDs answering every sample: a duty vector turning at a ramped frequency
    (0 -> 20 Hz electrical over 0.4 s), by cmd_seq."""
    duty_msg = db.get_message_by_name("DUTY_CMD")
    duties = {}
    for j in range(0, n, d):
        t = j * sc.machine.ts_s
        th = 2 * np.pi * 0.5 * 20.0 * t * t / 0.4
        dv = [0.5 + 0.08 * math.cos(th - i * 2 * np.pi / 3) for i in range(3)]
        data = duty_msg.encode(
            {"cmd_seq": j, "cmd_duty_a": dv[0], "cmd_duty_b": dv[1], "cmd_duty_c": dv[2],
             "cmd_enable": 1}
        )  # fmt: skip
        duties[j] = can.Message(arbitration_id=duty_msg.frame_id, data=data, is_extended_id=False)
    return duties


def _replay(sc, arm, duties, layout="fd", decimation=1, n=None):
    """Step the drive (plant + C core) through the scenario with a scripted host: ``arm``
    before period 0, the DUTY_CMD answering sample k-D before each sample boundary k.
    Returns the sample (SAMPLE_FD or SAMPLE_C_*) and STATUS payloads it sent, and the
    plant's frames per period."""
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.sim import DriveSetup

    ch = new_virtual_channel("fw-replay")
    fd = layout == "fd"
    drive = can.Bus(interface="virtual", channel=ch, fd=fd)
    host = can.Bus(interface="virtual", channel=ch, fd=fd)
    sent: dict[int, list[bytes]] = {i: [] for i in (ID_SAMPLE_FD, *CLASSIC_SAMPLE_IDS, ID_STATUS)}
    d = decimation
    try:
        emu = DriveEmulator(
            DriveSetup(sc), drive, lockstep=False, layout=layout, decimation=d, record=True,
            params={"HEARTBEAT_TIMEOUT_S": 0.0},  # the scripted host sends no heartbeat
        )  # fmt: skip
        host.send(arm)
        for k in range(sc.n_periods if n is None else n):
            if k >= d and k % d == 0:
                host.send(duties[k - d])
            emu.step()  # sends sample k, then takes what the host sent
            msg = host.recv(0.0)
            while msg is not None:
                if msg.arbitration_id in sent:
                    sent[msg.arbitration_id].append(bytes(msg.data))
                msg = host.recv(0.0)
    finally:
        drive.shutdown()
        host.shutdown()
    return sent, emu.recorded()[0]


_SAMPLE_SIGNALS = ("i_a", "i_b", "i_c", "v_ab", "v_bc", "v_ca", "vdc", "duty_a", "duty_b",
                   "duty_c", "encoder", "pwm_enabled")  # fmt: skip


def _check_samples_are_the_plants(db, sent, frames, layout, d):
    """Every sample the C core sent reports the plant's frames: sample j (period k = j D)
    currents, bus voltage and encoder of frame k, line voltages and duties averaged over
    the periods (t_(k-D), t_k], PWM on only if on in all of them
    (`fluxdrive.can.protocol.decimate_frames`, the offline reference; sample 0: frame 0),
    within one LSB per signal. The duties the core reports are what its timer held, the
    plant's frames what the plant was driven with: equal only if the SIL's timer model and
    the core agree on when a written duty applies."""
    from fluxdrive.can.protocol import FRAME_INDEX, decimate_frames

    ref = np.vstack([frames[:1], decimate_frames(frames, d)])
    pre = "" if layout == "fd" else "c_"
    ids = (ID_SAMPLE_FD,) if layout == "fd" else CLASSIC_SAMPLE_IDS
    got: dict[str, list[float]] = {}
    for aid in ids:
        msg = db.get_message_by_frame_id(aid)
        for p in sent[aid]:
            dec = msg.decode(p, decode_choices=False)
            for name in _SAMPLE_SIGNALS:
                if pre + name in dec:
                    got.setdefault(name, []).append(float(dec[pre + name]))
    m = min(len(v) for v in got.values())
    assert m >= min(ref.shape[0], 1000)
    worst = {}
    for name, values in got.items():
        sig = next(
            s for aid in ids for s in db.get_message_by_frame_id(aid).signals
            if s.name == pre + name
        )  # fmt: skip
        want = ref[:m, FRAME_INDEX["encoder_counts" if name == "encoder" else name]]
        if name == "encoder" and layout == "classic":  # 24 bits on the wire
            want = (want + 2**23) % 2**24 - 2**23
        worst[name] = float(np.max(np.abs(np.array(values[:m]) - want)) / sig.scale)
    print(f"{layout} D={d}: largest difference from the plant's frames [LSB] {worst}")
    assert max(worst.values()) <= 1.0 + 1e-6, worst
    return got


# in the parallel part: in-process and lockstep (each answer waited for), nothing timed
def test_sil_host_mode_closed_loop_and_samples_are_the_plants(db):
    """The drive (plant + C core), host mode, D = 1, FD on the virtual bus: (1) the 2 %
    case sensorless closes the loop through the bridge and the engine's observer and
    controller, in closed loop from 1 s, within 0.1 deg theta~ RMS of the in-process run
    of the same scenario (which has one period less of delay: there the controller runs in
    the period's interrupt; over CAN the host's answer to sample k is written at k+1 and
    applies from k+2); (2) an open-loop command stream: every SAMPLE_FD is the plant's
    frame within one LSB, the duties the core reports are those the plant was driven with."""
    from fluxdrive.can.loop import run_can_loop
    from fluxdrive.drive.sim import run_scenario
    from test_bench_bridge import short_2pct, theta_rms_deg

    sc = short_2pct(1.5)
    k0 = int(1.0 / sc.machine.ts_s)
    r = run_can_loop(sc)
    rms = theta_rms_deg(r.est[0], r.truth, k0)
    assert r.diagnostics["faults"] == 0 and r.diagnostics["malformed"] == 0
    assert np.all(r.ctrl[k0:, ctl.CO_MODE] == ctl.MODE_CLOSED_LOOP)
    ref = run_scenario(sc, progress=False)
    rms_ref = theta_rms_deg(ref.est[0], ref.truth, k0)
    print(f"theta RMS from 1.0 s: over CAN {rms:.4f} deg, in-process {rms_ref:.4f} deg")
    assert abs(rms - rms_ref) < 0.1

    n = 2000
    sent, frames = _replay(sc, _arm_msg(db), _turning_duties(db, sc, n, 1), n=n)
    got = _check_samples_are_the_plants(db, sent, frames, "fd", 1)
    assert sum(got["pwm_enabled"]) > 0.9 * len(got["pwm_enabled"])
    assert len(sent[ID_STATUS]) >= 1


# ---------------------------------------------------------------- split mode


def test_drive_param_ranges_are_the_engines(lib):
    """Every DRIVE_PARAM: the C core accepts exactly the engine's DRIVE_PARAM_RANGES, and
    refuses the ones in DRIVE_PARAMS_STOPPED while PWM is on."""
    _, mp = _card_mp()
    core = fw.FirmwareCore(mp)
    for name, (lo, hi) in ctl.DRIVE_PARAM_RANGES.items():
        assert core.param_write(name, lo) == "OK", name
        assert core.param_write(name, hi) == "OK", name
        assert core.param_write(name, hi * 1.001 + 1e-6) == "OUT_OF_RANGE", name
        if lo > 0.0:
            assert core.param_write(name, lo * 0.999) == "OUT_OF_RANGE", name
        assert core.param_write(name, float("nan")) == "NOT_FINITE", name
    assert set(ctl.DRIVE_PARAM_RANGES) == set(fw.PARAM_IDS) - set(fw.DRIVE_ONLY_PARAMS)
    card, mp = _card_mp()
    drive = _Drive(mp, ctl.ControllerConfig().to_params(card))
    drive.sample(np.zeros(3), card.dc_bus_v)
    drive.sample(np.zeros(3), card.dc_bus_v)
    assert drive.core.state()["pwm_enabled"]
    for name in fw.PARAM_IDS:
        value = drive.core.param_read(name)
        want = "NOT_WHILE_RUNNING" if name in ctl.DRIVE_PARAMS_STOPPED else "OK"
        want = "READ_ONLY" if name in fw.READ_ONLY_PARAMS else want
        assert drive.core.param_write(name, value) == want, name


def test_split_drive_is_the_engines_split_drive_step(lib, db):
    """Split mode, D = 4: the same frames and HOST_REFs (decoded as the wire carries them)
    into the engine's split_drive_take_reference / split_drive_step and into the C core;
    the duty the C core applies over [t_(k+1), t_(k+2)] is the engine's output for frame k
    to float32 rounding, over 1200 periods with late references (the extrapolation
    lengthens, the integrators rotate at each new one) and the hexagon limit reached."""
    card, mp = _card_mp()
    cp = ctl.ControllerConfig().to_params(card)
    cp[ctl.CP_REF_TIMEOUT] = 0.01
    cp[ctl.CP_TDCOMP] = 1.0e-6
    ts = card.ts_s
    d = 4
    core = fw.FirmwareCore(mp, decimation=d, pwm_period_ticks=1 << 24)
    for name, value in ctl.drive_param_values(cp).items():
        assert core.param_write(name, value) == "OK", name
    core.param_write("HEARTBEAT_TIMEOUT_S", 0.0)
    core.param_write("MAX_DUTY", 1.0)  # the engine has no duty cap: compare the loop alone
    arm = db.get_message_by_name("ARM_MODE")
    ref_msg = db.get_message_by_name("HOST_REF")
    data = arm.encode(
        {"arm": 1, "arm_key": ARM_KEY, "reset_fault": 0, "sample_layout": 0,
         "control_split": 1, "mode": 1, "cmd_timeout": 0, "decimation": d, "arm_counter": 0}
    )  # fmt: skip
    core.push(can.Message(arbitration_id=arm.frame_id, data=data, is_extended_id=False))
    cs, dr = np.zeros(ctl.CS_N), np.zeros(ctl.DR_N)
    ctl.split_drive_reset(cs, dr)
    out = np.zeros(ctl.CO_N)
    rng = np.random.default_rng(11)
    lsb, vlsb = float(mp[pl.MP_ADC_LSB]), float(mp[pl.MP_VDC_LSB])
    frame = np.zeros(pl.FR_N)
    we = 2 * np.pi * 40.0
    prev = None  # engine output of the previous period
    late = set(rng.choice(np.arange(2, 300), 40, replace=False).tolist())
    pending = []
    compared = saturated = 0
    for k in range(1200):
        if k % d == 0 and k >= d:
            j = k - d
            amp_iq = 4.0 if k < 600 else 20.0
            sig = {
                "ref_seq": j % 65536, "ref_id": float(rng.normal(0, 0.5)), "ref_iq": amp_iq,
                "ref_theta": float((we * j * ts + rng.normal(0, 0.01)) % (2 * np.pi)),
                "ref_omega": we + float(rng.normal(0, 2.0)), "ref_enable": 1,
            }  # fmt: skip
            pending.append((k + (2 if k // d in late else 0), ref_msg.encode(sig)))
        for due, payload in [p for p in pending if p[0] == k]:
            pending.remove((due, payload))
            r = ref_msg.decode(payload, decode_choices=False)
            row = np.zeros(ctl.RF_N)
            row[ctl.RF_ID_REF], row[ctl.RF_IQ_REF] = r["ref_id"], r["ref_iq"]
            row[ctl.RF_TH], row[ctl.RF_W], row[ctl.RF_EN] = r["ref_theta"], r["ref_omega"], 1.0
            row[ctl.RF_MODE] = ctl.MODE_CLOSED_LOOP
            ctl.split_drive_take_reference(cs, dr, row, (k - r["ref_seq"]) * ts)
            core.push(can.Message(arbitration_id=ref_msg.frame_id, data=payload, is_fd=True))
        th = we * k * ts
        i_abc = [3.0 * math.cos(th + 1.6 - j * 2 * math.pi / 3) + rng.normal(0, 0.2)
                 for j in range(3)]  # fmt: skip
        frame[pl.FR_IA : pl.FR_IC + 1] = _quantise(i_abc, lsb)
        bus = 1.0 if k < 600 else 0.4  # then a sagging bus: beyond the hexagon, limiter at work
        frame[pl.FR_VDC] = _quantise(bus * card.dc_bus_v * rng.uniform(0.98, 1.02), vlsb)
        ctl.split_drive_step(cs, cp, dr, frame, out)
        core.set_sample(frame, k * 100)
        core.period()
        core.pop_tx()
        duty_c, en_c = core.pwm()
        if prev is not None and prev[3] > 0.5:
            np.testing.assert_allclose(duty_c, prev[:3], atol=2e-5, err_msg=f"period {k}")
            assert en_c
            compared += 1
            saturated += math.hypot(out[ctl.CO_VD], out[ctl.CO_VQ]) > 0.55 * frame[pl.FR_VDC]
        prev = np.concatenate([out[ctl.CO_DA : ctl.CO_DC + 1], [out[ctl.CO_EN]]])
    assert not core.state()["fault_latched"] and cs[ctl.CS_MODE] != ctl.MODE_FAULT
    print(f"split: {compared} periods compared, {saturated} at the hexagon limit")
    assert compared > 1100 and saturated > 100


def test_c_mcu_answers_drive_params_between_periods(db):
    """DRIVE_PARAM over the bus to the drive (DriveEmulator): answered at once, between
    period interrupts (a host writing parameters never stalls a lockstep period), with
    the status and the value in effect."""
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.sim import DriveSetup
    from test_bench_bridge import short_2pct

    ch = new_virtual_channel("fw-param")
    drive = can.Bus(interface="virtual", channel=ch, fd=True)
    host = can.Bus(interface="virtual", channel=ch, fd=True)
    prm, ack = db.get_message_by_name("DRIVE_PARAM"), db.get_message_by_name("DRIVE_PARAM_ACK")
    try:
        ds = DriveSetup(short_2pct(0.6))  # the drive holds the scenario's design
        emu = DriveEmulator(ds, drive, lockstep=False, params=ctl.drive_param_values(ds.cp))
        asks = [(1, 1, 1, 2.5), (2, 9, 1, 50.0), (3, 99, 0, 0.0), (4, 3, 0, 0.0)]
        for seq, pid, write, value in asks:
            data = prm.encode({"prm_id": pid, "prm_seq": seq, "prm_write": write,
                               "prm_value": value})  # fmt: skip
            host.send(can.Message(arbitration_id=prm.frame_id, data=data, is_extended_id=False))
        emu._drain(0.2)
        emu._fw_feed()
        got = []
        msg = host.recv(0.5)
        while msg is not None:
            if msg.arbitration_id == ack.frame_id:
                got.append(ack.decode(bytes(msg.data), decode_choices=False))
            msg = host.recv(0.05)
    finally:
        drive.shutdown()
        host.shutdown()
    assert emu.k == 0  # no period ran
    assert [(a["pa_seq"], a["pa_status"]) for a in got] == [(1, 0), (2, 2), (3, 1), (4, 0)]
    assert got[0]["pa_value"] == 2.5 and got[1]["pa_value"] == pytest.approx(0.01)
    assert got[3]["pa_value"] == pytest.approx(emu.setup.cp[ctl.CP_L], rel=1e-6)  # the design


@pytest.mark.parametrize("layout,decimation", [("fd", 4), ("classic", 8)])
def test_decimated_samples_are_the_plants_windows(db, layout, decimation):
    """Decimation (window averages of line voltages and duties, PWM over the window) and
    the classic layout: an open-loop command stream (a duty vector turning at a ramped
    frequency, every sample answered) into the drive; every sample is the plant's window
    (`decimate_frames`) within one LSB per signal."""
    from test_bench_bridge import short_2pct

    sc = short_2pct(0.6)
    n, d = 4000, decimation
    arm = _arm_msg(db, layout, d)
    sent, frames = _replay(sc, arm, _turning_duties(db, sc, n, d), layout, d, n)
    got = _check_samples_are_the_plants(db, sent, frames, layout, d)
    assert sum(got["pwm_enabled"]) > 0.9 * len(got["pwm_enabled"])  # averages of real windows


def test_sil_calibration_removes_injected_current_offsets(db):
    """A drive that requires calibration refuses to arm (FAULT NOT_CALIBRATED); CALIBRATE_ADC
    with the plant's readings carrying 0.3 A / -0.2 A / 0.1 A of offset (PWM off, no
    current) averages 1000 periods, reports the offsets as read-only DRIVE_PARAMs (whole
    ADC counts here: the offsets are quantised readings), and afterwards the same readings
    are sampled as 0 A; arming then works."""
    _, mp = _card_mp()
    core = fw.FirmwareCore(mp, require_calibration=True)
    arm_msg = db.get_message_by_name("ARM_MODE")

    def arm(mode: int, arm_: int = 1, reset: int = 0) -> can.Message:
        data = arm_msg.encode(
            {"arm": arm_, "arm_key": ARM_KEY, "reset_fault": reset, "sample_layout": 0,
             "control_split": 0, "mode": mode, "cmd_timeout": 0, "decimation": 1,
             "arm_counter": 0}
        )  # fmt: skip
        return can.Message(arbitration_id=arm_msg.frame_id, data=data, is_extended_id=False)

    lsb = core.scales.current_lsb_a
    offsets = np.array([0.3, -0.2, 0.1])
    frame = np.zeros(pl.FR_N)
    frame[pl.FR_IA : pl.FR_IC + 1] = _quantise(offsets, lsb)
    frame[pl.FR_VDC] = 72.0

    def run(n: int) -> list[can.Message]:
        sent = []
        for _ in range(n):
            core.set_sample(frame, core.k * 100)
            core.period()
            sent += core.pop_tx()
        return sent

    core.push(arm(1))
    sent = run(2)
    faults = [db.decode_message(m.arbitration_id, m.data) for m in sent if m.arbitration_id == 0x10]
    assert str(faults[0]["fault_code"]) == "NOT_CALIBRATED" and not core.state()["armed"]
    core.push(arm(2, reset=1))
    run(1000)  # the request is taken in the background before the first of them
    assert core.param_read("CAL_DONE") == 1.0 and not core.state()["fault_latched"]
    got = np.array([core.param_read(f"CAL_OFFSET_{p}") for p in "ABC"])
    want = core.scales.current_mid_counts + np.round(offsets / lsb)
    np.testing.assert_array_equal(got, want)
    assert core.param_write("CAL_OFFSET_A", 0.0) == "READ_ONLY"
    sent = run(1)
    sample = db.decode_message(0x80, [m for m in sent if m.arbitration_id == 0x80][0].data)
    assert sample["i_a"] == sample["i_b"] == sample["i_c"] == 0.0
    core.push(arm(1))
    run(1)
    assert core.state()["armed"]


@pytest.mark.parametrize("case", ["break", "gate", "hot", "overrun", "saturated"])
def test_sil_fault_injection_through_the_binding(db, case):
    """FirmwareCore's fault injection (the SIL HAL's inputs a board wires to pins and
    timers): each condition, injected into a host-mode drive with PWM on, turns the PWM off
    in that very period and sends one FAULT frame with its code."""
    from fluxdrive.core import protocol_constants as pc

    card, mp = _card_mp()
    drive = _Drive(mp, ctl.ControllerConfig().to_params(card))
    for _ in range(3):
        assert drive.sample(np.zeros(3), card.dc_bus_v) == 0
    assert drive.core.pwm()[1]
    i_abc = np.zeros(3)
    temp_c = 35
    if case == "break":
        drive.core.set_break(15.0)  # the comparator below the software trip (18.9 A)
        i_abc[0] = 16.0
    elif case == "gate":
        drive.core.inject(gate_fault=True)
    elif case == "overrun":
        drive.core.inject(overrun=True)
    elif case == "saturated":
        i_abc[2] = -float(card.current_range_a)  # the converter's lower rail
    else:
        temp_c = 95
    k = drive.core.k
    data = drive.duty.encode(
        {"cmd_seq": k - 1, "cmd_duty_a": 0.5, "cmd_duty_b": 0.5, "cmd_duty_c": 0.5,
         "cmd_enable": 1}
    )  # fmt: skip
    drive.core.push(can.Message(arbitration_id=drive.duty.frame_id, data=data))
    drive.frame[pl.FR_IA : pl.FR_IC + 1] = _quantise(i_abc, float(mp[pl.MP_ADC_LSB]))
    drive.core.set_sample(drive.frame, k * 100, temp_c=temp_c)
    drive.core.period()
    faults = [
        db.decode_message(m.arbitration_id, m.data, decode_choices=False)
        for m in drive.core.pop_tx()
        if m.arbitration_id == pc.ID_FAULT
    ]
    want = {"break": pc.FAULT_OVERCURRENT, "gate": pc.FAULT_GATE_DRIVER,
            "hot": pc.FAULT_OVERTEMPERATURE, "overrun": pc.FAULT_DEADLINE_MISSED,
            "saturated": pc.FAULT_ADC_FAULT}[case]  # fmt: skip
    assert [f["fault_code"] for f in faults] == [want]
    assert drive.core.pwm()[1] is False and drive.core.state()["fault_latched"]
    if case == "break":
        assert faults[0]["fault_detail"] == 3  # no phase: the hardware path
