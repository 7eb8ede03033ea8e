"""The NUCLEO-G474RE board port (firmware/board/nucleo_g474) and the virtual board that runs
its image (fluxdrive.can.vboard): register data generated from the pinned stm32g4 crate,
the image built with warnings as errors, booted on the emulated Cortex-M4F (clock tree,
timer, ADC trigger, CAN bit timing read back from the registers it wrote), the period
interrupt on the timer's update with the compare preload, and the split-mode closed loop
in-process against the C core's software-in-the-loop run. No ROS."""

from __future__ import annotations

import functools
import shutil

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
