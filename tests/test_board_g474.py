"""The NUCLEO-G474RE board port (firmware/board/nucleo_g474) and the virtual board that runs
its image (fluxdrive.can.vboard): register data generated from the pinned stm32g4 crate,
the image built with warnings as errors, booted on the emulated Cortex-M4F (clock tree,
timer, ADC trigger, CAN bit timing read back from the registers it wrote), the period
interrupt on the timer's update with the compare preload, and the split-mode closed loop
in-process against the C core's software-in-the-loop run, and the parameter storage in
flash on the virtual board's FLASH interface (a save, a power cycle, a corrupted page, a
power loss in the middle of a save). No ROS."""

from __future__ import annotations

import functools
import shutil
import struct

import numpy as np
import pytest
from fluxdrive.can import g474_regmap as rm
from fluxdrive.can import g474gen
from fluxdrive.can.vboard import TIM1_ARR, VirtualBoard, build_board, elf_symbols
from fluxdrive.drive import plant as pl
from fluxdrive.drive.sim import DriveSetup

SYSCLK_HZ = 170e6


@pytest.mark.skipif(shutil.which("cargo") is None, reason="cargo (the register data) missing")
def test_register_map_is_generated_from_the_pinned_crate():
    """g474_regs.h and g474_regmap.py are what the generator makes from the stm32g4 crate
    pinned in tools/g474-registers/Cargo.toml (fetched by cargo)."""
    crate = g474gen.crate_dir()
    header, pymap = g474gen.render(g474gen.generate(crate), crate.name.split("-", 1)[1])
    assert g474gen.HEADER.read_text() == header
    assert g474gen.PYMAP.read_text() == pymap
    # a few values of RM0440 the data must agree with
    assert rm.BASE["TIM1"] == 0x40012C00 and rm.BASE["FDCAN1"] == 0x40006400
    assert rm.REG["ADC1_JDR1"][0] == 0x50000080 and rm.IRQ["ADC1_2"] == 18
    assert rm.FIELD["TIM1_BDTR_MOE"] == (15, 1) and rm.FIELD["FDCAN1_DBTP_TDC"] == (23, 1)


def _field(v: int, name: str) -> int:
    pos, width = rm.FIELD[name]
    return (v >> pos) & ((1 << width) - 1)


@pytest.fixture(scope="module")
def board():
    from test_split_can import _split_case

    return VirtualBoard(DriveSetup(_split_case(1.0)).mp, decimation=4)


def test_image_builds_and_boots_on_the_virtual_board(board):
    """Built with -Werror (build_board fails otherwise); the reset handler runs to the
    background loop: 24 MHz HSE -> PLL /6 x85 /2 = 170 MHz, 4 flash wait states; TIM1
    centre-aligned at 10 kHz with preload and deadtime; ADC injected on TIM1 TRGO; FDCAN
    1/5 Mbit/s with delay compensation; every vector a Thumb address in flash."""
    syms = elf_symbols(build_board() / "fd_board_d4.elf")
    reg = {name: board.regs[addr] for name, (addr, _reset) in rm.REG.items()}
    pll = reg["RCC_PLLCFGR"]
    m = _field(pll, "RCC_PLLCFGR_PLLM") + 1
    n = _field(pll, "RCC_PLLCFGR_PLLN")
    r = 2 * (_field(pll, "RCC_PLLCFGR_PLLR") + 1)
    assert _field(pll, "RCC_PLLCFGR_PLLSRC") == 3 and _field(pll, "RCC_PLLCFGR_PLLREN") == 1
    assert 24e6 / m * n / r == SYSCLK_HZ and 24e6 / m * n <= 344e6
    assert (
        _field(reg["RCC_CFGR"], "RCC_CFGR_SWS") == 3
        and _field(reg["RCC_CFGR"], "RCC_CFGR_HPRE") == 0
    )
    assert _field(reg["FLASH_ACR"], "FLASH_ACR_LATENCY") == 4
    assert board.board_state()["clock_source"] == 1  # the HSE started
    # TIM1: centre-aligned 1, ARR 8500 -> 170 MHz / (2 * 8500) = 10 kHz, one update per period
    assert _field(reg["TIM1_CR1"], "TIM1_CR1_CMS") == 1 and reg["TIM1_ARR"] == TIM1_ARR
    assert SYSCLK_HZ / (2 * reg["TIM1_ARR"]) == 10e3 and reg["TIM1_RCR"] == 1
    for ch in (1, 2):
        assert _field(reg["TIM1_CCMR1_OUTPUT"], f"TIM1_CCMR1_OUTPUT_OC{ch}PE") == 1
    assert _field(reg["TIM1_CCMR2_OUTPUT"], "TIM1_CCMR2_OUTPUT_OC3PE") == 1
    dtg = _field(reg["TIM1_BDTR"], "TIM1_BDTR_DTG")
    assert dtg >> 6 == 0b11 and abs((32 + (dtg & 31)) * 8 / SYSCLK_HZ - 2.0e-6) < 8 / SYSCLK_HZ
    assert (
        _field(reg["TIM1_BDTR"], "TIM1_BDTR_BKE") == 1
        and _field(reg["TIM1_AF1"], "TIM1_AF1_BKCMP1E") == 1
    )
    assert _field(reg["TIM1_CR2"], "TIM1_CR2_MMS") == 2  # TRGO = update
    jsqr = reg["ADC1_JSQR"]
    assert _field(jsqr, "ADC1_JSQR_JL") == 3 and _field(jsqr, "ADC1_JSQR_JEXTSEL") == 0
    assert _field(jsqr, "ADC1_JSQR_JEXTEN") == 1
    nb, db = reg["FDCAN1_NBTP"], reg["FDCAN1_DBTP"]
    nbit = 3 + _field(nb, "FDCAN1_NBTP_NTSEG1") + _field(nb, "FDCAN1_NBTP_NTSEG2")
    dbit = 3 + _field(db, "FDCAN1_DBTP_DTSEG1") + _field(db, "FDCAN1_DBTP_DTSEG2")
    assert SYSCLK_HZ / ((_field(nb, "FDCAN1_NBTP_NBRP") + 1) * nbit) == 1e6
    assert SYSCLK_HZ / ((_field(db, "FDCAN1_DBTP_DBRP") + 1) * dbit) == 5e6
    assert _field(db, "FDCAN1_DBTP_TDC") == 1 and _field(reg["FDCAN1_TDCR"], "FDCAN1_TDCR_TDCO") > 0
    assert board.vectors[16 + rm.IRQ["ADC1_2"]] == syms["ADC1_2_IRQHandler"][0] | 1
    assert all(v & 1 and 0x08000000 <= v < 0x08080000 for v in board.vectors[1:7])


def test_period_interrupt_runs_on_each_update_and_compare_is_preloaded(board):
    """Each period: the update event starts the conversions and the period interrupt runs
    the core once (its period counter and the board's agree); a compare value written in
    period k is active only from the update of period k+1 (TIM1 preload)."""
    frame = np.zeros(pl.FR_N)
    frame[pl.FR_VDC] = 72.0
    k0, n0 = board.k, len(board.isr_instructions)
    for i in range(8):
        board.set_sample(frame, 100 * i)
        board.period()
    assert board.k - k0 == 8 and board.board_state()["periods"] == board.k
    assert len(board.isr_instructions) - n0 == 8 and min(board.isr_instructions[n0:]) > 100
    ccr1 = rm.REG["TIM1_CCR1"][0]
    before = board.pwm()[0][0]  # PWM off: the core writes duty 0.5
    board.regs[ccr1] = TIM1_ARR // 4  # as a write in this period's interrupt would
    assert board.pwm()[0][0] == before == 0.5  # the active compare: still the old one
    board.set_sample(frame, 900)
    board.period()
    assert board.pwm()[0][0] == pytest.approx(0.75)  # PWM mode 2: (ARR - CCR) / ARR
    assert 0 < board.stack_high_water() < 4096 and board.iwdg_resets == 0


def test_split_closed_loop_on_the_virtual_board_matches_sil(monkeypatch):
    """The paper's 2 % drive in split mode at D = 4 through the bridge (in-process, no ROS):
    the board image on the virtual board as the MCU (its duties through the timer's
    preload: one period later than the SIL HAL applies them) and the C core's SIL build:
    θ̃ RMS over the last 0.5 s within 0.1° of each other, closed loop, no fault."""
    from fluxdrive.can import vboard
    from fluxdrive.can.loop import run_can_loop
    from fluxdrive.drive.control import CO_MODE, MODE_CLOSED_LOOP
    from fluxdrive.drive.observers import ES_TH
    from fluxdrive.drive.plant import TR_THETA_E
    from test_split_can import D, _split_case, _theta_rms_deg

    # no instruction counting here (the closed loop is the point; benchmark firmware counts)
    monkeypatch.setattr(vboard, "VirtualBoard", functools.partial(VirtualBoard, measure=False))
    sc = _split_case(1.5)
    k_win = int(1.0 / sc.machine.ts_s) // D
    rms = {}
    for mcu in ("c", "pil"):
        r = run_can_loop(sc, emulator_kw={"mcu": mcu})
        m = r.est.shape[1]
        assert r.emulator_stats["faults"] == 0 and r.emulator_stats["lockstep_timeouts"] == 0
        assert np.all(r.ctrl[k_win:, CO_MODE] == MODE_CLOSED_LOOP)
        rms[mcu] = _theta_rms_deg(r.est[0, k_win:, ES_TH], r.truth[::D][k_win:m, TR_THETA_E])
    print(f"theta~ RMS from 1.0 s: SIL {rms['c']:.4f} deg, virtual board {rms['pil']:.4f} deg")
    assert abs(rms["pil"] - rms["c"]) < 0.1


def _fault_frames(board) -> list[dict]:
    from fluxdrive.can.protocol import ID_FAULT, get_protocol

    msg = get_protocol().message("FAULT")
    return [
        msg.decode(bytes(m.data), decode_choices=False)
        for m in board.pop_tx()
        if m.arbitration_id == ID_FAULT
    ]


@pytest.mark.parametrize("fault", ["break", "gate"])
def test_fault_inputs_latch_on_the_virtual_board(fault):
    """The hardware inputs of the port, injected on the virtual board: a phase current above
    COMP1's threshold (DAC3 at 19 A) trips TIM1's break at the update (MOE cleared before the
    interrupt runs, the break interrupt counted) and the core latches OVERCURRENT with the
    break's detail in that period's interrupt; nFAULT low latches GATE_DRIVER. Each sends a
    FAULT frame; PWM stays off."""
    from fluxdrive.core.protocol_constants import FAULT_GATE_DRIVER, FAULT_OVERCURRENT
    from test_split_can import _split_case

    vb = VirtualBoard(DriveSetup(_split_case(1.0)).mp, decimation=4)
    frame = np.zeros(pl.FR_N)
    frame[pl.FR_VDC] = 72.0
    for i in range(4):
        vb.set_sample(frame, 100 * i)
        vb.period()
    vb.pop_tx()
    bdtr = rm.REG["TIM1_BDTR"][0]
    vb.regs[bdtr] |= 1 << rm.FIELD["TIM1_BDTR_MOE"][0]  # outputs on, as after an arming
    if fault == "break":
        frame[pl.FR_IA], frame[pl.FR_IB] = 19.5, -19.5  # above DAC3's 19 A, below full scale
    else:
        vb.gate_fault = True
    vb.set_sample(frame, 500)
    vb.period()
    st = vb.state()
    faults = _fault_frames(vb)
    assert st["fault_latched"] and not st["pwm_enabled"] and not vb.pwm()[1]
    if fault == "break":
        assert vb.break_trips == 1 and vb.board_state()["break_trips"] == 1
        assert st["fault_code"] == FAULT_OVERCURRENT
        assert [(f["fault_code"], f["fault_detail"]) for f in faults] == [(FAULT_OVERCURRENT, 3)]
    else:
        assert vb.break_trips == 0 and st["fault_code"] == FAULT_GATE_DRIVER
        assert [f["fault_code"] for f in faults] == [FAULT_GATE_DRIVER]


def test_instruction_trace_adds_up_to_the_count():
    """trace=True keeps each period interrupt's executed blocks (for a cycle model): their
    Thumb instructions add up to the interrupt's instruction count."""
    from fluxdrive.can.vboard import _thumb_count
    from test_split_can import _split_case

    vb = VirtualBoard(DriveSetup(_split_case(1.0)).mp, decimation=4, trace=True)
    frame = np.zeros(pl.FR_N)
    frame[pl.FR_VDC] = 72.0
    for i in range(6):
        vb.set_sample(frame, 100 * i)
        vb.period()
    assert len(vb.isr_blocks) == len(vb.isr_instructions) == 6
    for blocks, n in zip(vb.isr_blocks, vb.isr_instructions, strict=True):
        total = sum(
            c * _thumb_count(bytes(vb.mu.mem_read(a, s)))  # flash or CCM SRAM
            for (a, s), c in blocks.items()
        )
        assert total == n


# ---------------------------------------------------------------------- parameter storage

_STORE_PAGE = 0x0807F000 - 0x08000000  # bank 2, page 126 (fd_board.h), in the flash image


def _param(vb: VirtualBoard, name: str, value: float | None = None) -> tuple[str, float]:
    """A DRIVE_PARAM over the bus (a write with ``value``, else a read) handled by the
    board's background context; its DRIVE_PARAM_ACK as (status, value in effect)."""
    import can
    from fluxdrive.can.firmware import PARAM_IDS
    from fluxdrive.can.protocol import ID_DRIVE_PARAM, ID_DRIVE_PARAM_ACK, get_protocol
    from fluxdrive.core.protocol_constants import PA_CHOICES

    proto = get_protocol()
    data = proto.message("DRIVE_PARAM").encode(
        {
            "prm_id": PARAM_IDS[name],
            "prm_seq": 1,
            "prm_write": int(value is not None),
            "prm_value": 0.0 if value is None else value,
        }
    )
    vb.handle_now(can.Message(arbitration_id=ID_DRIVE_PARAM, data=data, is_extended_id=False))
    acks = [
        proto.message("DRIVE_PARAM_ACK").decode(bytes(m.data), decode_choices=False)
        for m in vb.pop_tx()
        if m.arbitration_id == ID_DRIVE_PARAM_ACK
    ]
    assert len(acks) == 1
    return PA_CHOICES[int(acks[0]["pa_status"])], float(acks[0]["pa_value"])


# DRIVE_PARAM PARAM_SOURCE: where the parameters at boot came from (fd_core.h)
PRM_SOURCE_DEFAULTS, PRM_SOURCE_STORED, PRM_SOURCE_BAD_CRC = 0.0, 1.0, 2.0


def _storage_board(flash_image: bytes | None = None) -> VirtualBoard:
    from test_split_can import _split_case

    mp = DriveSetup(_split_case(1.0)).mp
    return VirtualBoard(mp, decimation=4, measure=False, flash_image=flash_image)


def test_flash_register_map_and_reset_state():
    """The FLASH interface's registers the storage uses, at RM0440's addresses (3.7) with
    their reset values: locked, dual-bank option bytes (DBANK)."""
    assert rm.REG["FLASH_KEYR"][0] == 0x40022008 and rm.REG["FLASH_SR"][0] == 0x40022010
    assert rm.REG["FLASH_CR"] == (0x40022014, 0xC0000000)  # LOCK and OPTLOCK set
    assert rm.REG["FLASH_OPTR"][0] == 0x40022020
    assert _field(rm.REG["FLASH_OPTR"][1], "FLASH_OPTR_DBANK") == 1
    assert rm.FIELD["FLASH_CR_PNB"] == (3, 7) and rm.FIELD["FLASH_SR_BSY"] == (16, 1)


def test_saved_parameters_survive_a_power_cycle():
    """PARAM_SAVE over the bus programs the set into flash (unlock, page erase, double-words,
    the valid flag last, locked again); a new board from that flash image (a power cycle)
    boots with the saved values and says where they came from (PARAM_SOURCE 1). A second
    save goes to the other page with the next sequence number, and the newer set wins."""
    vb = _storage_board()
    assert _param(vb, "PARAM_SOURCE") == ("OK", PRM_SOURCE_DEFAULTS)  # erased flash
    assert vb.board_state()["store_state"] == 0
    default = _param(vb, "I2T_LIMIT_PU2S")[1]
    assert _param(vb, "I2T_LIMIT_PU2S", 42.5) == ("OK", 42.5)
    assert _param(vb, "REF_TIMEOUT_S", 0.004) == ("OK", pytest.approx(0.004))
    assert _param(vb, "PARAM_SAVE", 1.0)[0] == "OK"
    bs = vb.board_state()
    assert (bs["store_saves"], bs["store_errors"], bs["store_seq"]) == (1, 0, 1)
    # the page: magic, version | length, sequence and complement; the rest erased
    img = vb.flash_image()
    magic, ver_len, seq, nseq = struct.unpack_from("<4I", img, _STORE_PAGE)
    assert magic == 0x53504446 and ver_len >> 16 == 1 and (seq, nseq) == (1, 0xFFFFFFFE)
    assert img[_STORE_PAGE + 2048 : _STORE_PAGE + 4096] == b"\xff" * 2048
    regs = vb.regs
    assert regs[rm.REG["FLASH_CR"][0]] & (1 << 31)  # locked again
    assert regs[rm.REG["FLASH_SR"][0]] == 0  # no error flag left

    vb2 = _storage_board(img)  # power cycle
    assert _param(vb2, "PARAM_SOURCE") == ("OK", PRM_SOURCE_STORED)
    assert _param(vb2, "I2T_LIMIT_PU2S") == ("OK", 42.5)
    assert _param(vb2, "REF_TIMEOUT_S")[1] == pytest.approx(0.004)
    assert _param(vb2, "I2T_LIMIT_PU2S", 50.0)[0] == "OK"
    assert _param(vb2, "PARAM_SAVE", 1.0)[0] == "OK"
    assert vb2.board_state()["store_seq"] == 2
    img2 = vb2.flash_image()
    assert struct.unpack_from("<I", img2, _STORE_PAGE + 2048 + 8)[0] == 2  # the other page
    assert img2[_STORE_PAGE : _STORE_PAGE + 2048] == img[_STORE_PAGE : _STORE_PAGE + 2048]
    vb3 = _storage_board(img2)
    assert _param(vb3, "I2T_LIMIT_PU2S") == ("OK", 50.0) and default != 50.0


def test_a_corrupted_page_boots_with_the_defaults_and_says_so():
    """One bit flipped in the only stored set: its CRC fails, the board boots on the
    defaults and reports it (PARAM_SOURCE 2, the board's store state 'bad'); a new save
    still works (the other page)."""
    vb = _storage_board()
    default = _param(vb, "I2T_LIMIT_PU2S")[1]
    _param(vb, "I2T_LIMIT_PU2S", 42.5)
    assert _param(vb, "PARAM_SAVE", 1.0)[0] == "OK"
    img = bytearray(vb.flash_image())
    img[_STORE_PAGE + 16 + 40] ^= 0x04  # a bit of the record
    vb2 = _storage_board(bytes(img))
    assert _param(vb2, "PARAM_SOURCE") == ("OK", PRM_SOURCE_BAD_CRC)
    assert vb2.board_state()["store_state"] == 2
    assert _param(vb2, "I2T_LIMIT_PU2S") == ("OK", default)
    assert _param(vb2, "PARAM_SAVE", 1.0)[0] == "OK"
    assert _param(_storage_board(vb2.flash_image()), "PARAM_SOURCE")[1] == PRM_SOURCE_STORED


@pytest.mark.parametrize("cut_after", [1, 3, 12, -1])
def test_a_power_loss_during_a_save_keeps_the_previous_set(cut_after):
    """The supply goes after `cut_after` flash operations of a save (1: the page erase; 3:
    the header; 12: within the record; -1: all but the valid flag): the next boot finds the
    previous set intact on the other page and boots with it."""
    vb = _storage_board()
    _param(vb, "I2T_LIMIT_PU2S", 42.5)
    assert _param(vb, "PARAM_SAVE", 1.0)[0] == "OK"
    n_save = vb.flash_operations  # erase, 2 header, the record's double-words, valid flag
    length = struct.unpack_from("<I", vb.flash_image(), _STORE_PAGE + 4)[0] & 0xFFFF
    assert n_save == 1 + 2 + -(-length // 8) + 1
    _param(vb, "I2T_LIMIT_PU2S", 50.0)
    vb.cut_power_after(cut_after % n_save)
    _param(vb, "PARAM_SAVE", 1.0)  # the board is dark: what it answers does not matter
    vb2 = _storage_board(vb.flash_image())
    assert _param(vb2, "I2T_LIMIT_PU2S") == ("OK", 42.5)
    assert vb2.board_state()["store_seq"] == 1


def test_the_flash_model_refuses_what_the_silicon_refuses():
    """RM0440 3.3.5-3.3.7 on the model, as the CPU's stores reach it: a write to the flash
    without PG sets PGSERR; a double-word that is not erased PROGERR; a half-word SIZERR;
    an erase outside the storage pages (the image's own) WRPERR; a wrong key locks FLASH_CR
    until reset (KEY1, KEY2 then unlock nothing)."""
    vb = _storage_board()
    _param(vb, "PARAM_SAVE", 1.0)  # page 126 holds a set
    cr, sr, keyr = (rm.REG[f"FLASH_{n}"][0] for n in ("CR", "SR", "KEYR"))
    bit = {n: 1 << rm.FIELD[f"FLASH_SR_{n}"][0] for n in ("PGSERR", "PROGERR", "SIZERR", "WRPERR")}

    def store(addr: int, value: int, size: int = 4) -> None:  # a CPU store to a register
        vb._write(vb.mu, addr & 0xFFF, size, value, addr & ~0xFFF)

    def program(off: int, value: int, size: int = 4) -> None:  # a CPU store to the flash
        vb._flash_write(vb.mu, off, size, value, None)

    def flags() -> int:
        v = vb.regs[sr]
        store(sr, v)  # rc_w1: cleared
        return v

    program(2048, 0)
    assert flags() == bit["PGSERR"]  # locked, PG not set
    store(keyr, 0x45670123)
    store(keyr, 0xCDEF89AB)
    assert not vb.regs[cr] & (1 << 31)  # unlocked
    store(cr, 1)  # PG
    program(0, 0x12345678)
    program(4, 0x9ABCDEF0)
    assert flags() == bit["PROGERR"]  # the header double-word is programmed already
    program(2048, 0x1234, size=2)
    assert flags() == bit["SIZERR"]
    store(cr, (1 << 1) | (5 << 3) | (1 << 16))  # PER, bank 1 page 5 (the image), STRT
    assert flags() == bit["WRPERR"]
    store(cr, 1 << 31)  # LOCK
    store(keyr, 0x45670123)
    store(keyr, 0x11111111)  # a wrong second key
    store(keyr, 0x45670123)
    store(keyr, 0xCDEF89AB)
    assert vb.regs[cr] & (1 << 31)  # locked until the next reset


def test_can_emulator_keeps_the_board_flash_across_runs(tmp_path, capsys):
    """`can-emulator --mcu pil --flash FILE`: the board boots from FILE and writes its flash
    back, so a set saved in one run is the next run's; each boot says where its parameters
    came from on the console, a corrupted set included; a file of another size is one
    line, exit 2."""
    from fluxdrive.cli.canemulator import main

    f = tmp_path / "board.flash"
    args = ["--mcu", "pil", "--interface", "virtual", "--channel", f"flash-{tmp_path.name}"]
    args += ["--decimation", "4", "--periods", "4", "--lockstep-wait", "0.01", "--flash", str(f)]
    assert main(args) == 0
    assert "board parameters: the defaults (nothing stored in flash)" in capsys.readouterr().err
    vb = _storage_board(f.read_bytes())  # a save on the board that run left
    _param(vb, "I2T_LIMIT_PU2S", 42.5)
    assert _param(vb, "PARAM_SAVE", 1.0)[0] == "OK"
    f.write_bytes(vb.flash_image())
    assert main(args) == 0
    assert "board parameters: the stored set 1 (flash, CRC good)" in capsys.readouterr().err
    assert _param(_storage_board(f.read_bytes()), "I2T_LIMIT_PU2S") == ("OK", 42.5)
    img = bytearray(f.read_bytes())
    img[_STORE_PAGE + 16 + 40] ^= 0x04
    f.write_bytes(bytes(img))
    assert main(args) == 0
    assert "no intact set (bad CRC; PARAM_SOURCE 2)" in capsys.readouterr().err
    f.write_bytes(b"\xff" * 1024)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"can-emulator: --flash {f}: ")
