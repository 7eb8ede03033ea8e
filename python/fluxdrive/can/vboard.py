"""The virtual board: the board image that would be flashed, run on an instruction-set
emulator with models of the STM32G474's peripherals, as the drive's MCU.

:func:`build_board` cross-compiles ``firmware/board/nucleo_g474`` (Debian's
``arm-none-eabi-gcc``, warnings as errors) into ``.ws/firmware/board``: one image per
decimation D the bench uses (``fd_board_d1.elf``, ``fd_board_d4.elf``).

:class:`VirtualBoard` loads such an ELF into Unicorn (a Cortex-M4 with its FPU), runs its
reset handler (clock tree, peripheral set-up, the drive core's init) until the background
loop's idle point (``fd_board_wait``), and then, per PWM period, does what the silicon does
(peripheral behaviour from RM0440; register addresses, reset values and bit fields from
:mod:`fluxdrive.can.g474_regmap`, generated from the stm32g4 crate):

* TIM1 update event at the valley t_k: the preloaded compare values (CCR1..3 written by the
  interrupt of t_(k-1)) become the active ones for [t_k, t_(k+1)];
* its TRGO resets the three line-voltage capture timers and starts the injected
  conversions: ADC1 JDR1..4 take the phase currents and the bus voltage of sample k (the
  plant's frame, in the plant's own ADC counts), ADC2 JDR1 the stage temperature;
* the capture timers hold the comparator edges of the period just ended: one pulse per
  line, centred on the carrier peak, as wide as the plant's average line voltage says
  (CCR1/CCR2 rising/falling edge of the positive comparator, CCR3/CCR4 of the negative);
* COMP1 (over-current) against DAC3's threshold: above it the TIM1 break clears MOE at
  once (PWM off for the whole period) and the break interrupt runs;
* ADC1's end of injected sequence raises the period interrupt (``ADC1_2_IRQHandler``,
  the vector table's entry): the emulator stacks the exception frame (26 words: the FP
  context is active) below the background loop's stack and runs the handler until it
  returns; then the background loop runs until it is idle again;
* FDCAN1: the message RAM is memory; TXBAR takes a TX buffer element to the bus, received
  frames that pass the standard-id filters go into RX FIFO 0 (3 elements; while it is full
  a frame waits on the bus side and enters when RXF0A releases an element: in lockstep the
  host's frames pile up between interrupts, which a free-running bus spreads out);
* IWDG: refreshes are counted; a 10 ms gap counts a watchdog reset (none expected).
* FLASH: the parameter storage's two pages (bank 2, pages 126 and 127; the rest of the
  array is the image, read-only here) behind the FLASH interface (RM0440 3.3.5-3.3.7, 3.7):
  KEYR's KEY1/KEY2 sequence clears CR.LOCK (a wrong one locks it until reset), CR.PER with
  PNB/BKER and STRT erases a page, CR.PG with two word writes programs a double-word that
  is erased; SR's error flags as the manual sets them (PGSERR, SIZERR, PGAERR, PROGERR,
  WRPERR for a page outside the storage), EOP only with EOPIE. Operations complete at once
  (BSY never reads set). :meth:`VirtualBoard.flash_image` and ``flash_image=`` carry the
  flash across a power cycle; :meth:`VirtualBoard.cut_power_after` cuts the supply in the
  middle of a save.

:meth:`VirtualBoard.pwm` answers with the active compare values and MOE: the plant gets
the duty the interrupt of t_(k-1) computed, as on the real timer with preload.

Measured per period interrupt: executed instructions (a block hook counts each translated
block's Thumb instructions) and, at the end, the main stack's high-water mark (the start-up
code paints the stack; the first overwritten word from the bottom). The hardware exception
entry/exit is modelled, not executed: its stacked frame counts in the high-water mark, its
cycles are not in the instruction count.

It offers :class:`fluxdrive.can.firmware.FirmwareCore`'s interface, so
``DriveEmulator(mcu="pil")`` runs it in closed loop with the project's plant.
"""

from __future__ import annotations

import collections
import struct
from pathlib import Path
from typing import Any

import can
import numpy as np

from fluxdrive.can import g474_regmap as rm
from fluxdrive.can.elf import elf_symbols, read_elf, thumb_pcs
from fluxdrive.can.firmware import _STAT_NAMES, FIRMWARE_DIR, PARAM_IDS, sensor_scales
from fluxdrive.can.protocol import ID_DUTY_CMD, ID_HOST_REF, get_protocol
from fluxdrive.core.paths import ROOT
from fluxdrive.core.protocol_constants import PA_CHOICES
from fluxdrive.drive import plant as pl

__all__ = [
    "BOARD_DECIMATIONS",
    "VirtualBoard",
    "board_build_dir",
    "build_board",
    "elf_symbols",
    "thumb_pcs",
]

BOARD_DIR = FIRMWARE_DIR / "board" / "nucleo_g474"
BOARD_DECIMATIONS = (1, 4)
"""The decimations a board image is built for (D is fixed at build time)."""
SYSCLK_HZ = 170e6
PWM_HZ = 10e3
TIM1_ARR = int(SYSCLK_HZ / (2 * PWM_HZ))  # 8500
CAPTURE_TICKS = 2 * TIM1_ARR
ADC_MID = 2048
TEMP_ZERO_COUNTS, TEMP_COUNTS_PER_C = 500, 10
STACK_PAINT = 0xA5A5A5A5
EXC_FRAME_BYTES = 104  # 8 basic + 18 FP words (lazy FP stacking reserves them)
IWDG_PERIODS = 100  # 10 ms at 10 kHz
_RETURN = 0x0807EF00  # where an emulated exception / call returns to (unused flash)
_SCRATCH = 0x20017000  # frames handed to the core between interrupts
_FLASH, _FLASH_SIZE = 0x08000000, 512 * 1024
# the parameter storage pages (fd_board.h): bank 2's pages 126 and 127 (dual-bank mode:
# two banks of 256 KB in 2 KB pages, RM0440 3.3.1); the FLASH interface's keys (3.3.5)
_PAGE_BYTES, _BANK_BYTES = 2048, 256 * 1024
_STORE, _STORE_SIZE = _FLASH + _BANK_BYTES + 126 * _PAGE_BYTES, 2 * _PAGE_BYTES
_FLASH_KEY1, _FLASH_KEY2 = 0x45670123, 0xCDEF89AB
_RAM, _RAM_SIZE = 0x20000000, 96 * 1024
_CCM, _CCM_SIZE = 0x10000000, 32 * 1024  # the period interrupt's code (sections.ld)
_PAGES = (0x40000000, 0x40003000, 0x40006000, 0x40007000, 0x40010000, 0x40012000,
          0x40013000, 0x40021000, 0x40022000, 0x48000000, 0x50000000, 0x50001000,
          0xE000E000)  # fmt: skip
_CPACR = 0xE000ED88
_NVIC_ISER0 = 0xE000E100
_MRAM_RF0, _MRAM_TXB, _MRAM_ELEM = 0x0B0, 0x278, 72
_DLC_LEN = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def board_build_dir() -> Path:
    return ROOT / ".ws" / "firmware" / "board"


def build_board(force: bool = False) -> Path:
    """Cross-compile the board images (a no-op while no firmware source changed)."""
    from fluxdrive.can.firmware_target import cross_build

    elfs = [f"fd_board_d{d}.elf" for d in BOARD_DECIMATIONS]
    return cross_build(BOARD_DIR, board_build_dir(), elfs, "board image", force)


def _thumb_count(code: bytes) -> int:
    """Thumb instructions in a block of code."""
    return len(thumb_pcs(0, code))


# ---------------------------------------------------------------------- the board


def _reg(name: str) -> int:
    return rm.REG[name][0]


def _bit(name: str) -> int:
    pos, width = rm.FIELD[name]
    return ((1 << width) - 1) << pos


class VirtualBoard:
    """The board image on Unicorn with the peripheral models (see the module doc); the
    interface of :class:`fluxdrive.can.firmware.FirmwareCore`."""

    def __init__(
        self,
        mp: np.ndarray,
        *,
        decimation: int = 4,
        classic: bool = False,
        cmd_timeout_s: float = 1e-3,
        measure: bool = True,
        elf: Path | None = None,
        bootstrap_periods: int = 0,
        trace: bool = False,
        flash_image: bytes | None = None,
    ) -> None:
        # flash_image: the flash a board left (:meth:`flash_image`): this board is that one
        # after a power cycle (the ELF programmed over it leaves it as it was)
        # bootstrap_periods: FirmwareCore's knob; the image's is fixed at build (fd_board.h)
        import unicorn as uc
        from unicorn import arm_const as ac

        if classic:
            raise ValueError("the board image sends the FD sample layout only")
        if elf is None:
            if decimation not in BOARD_DECIMATIONS:
                raise ValueError(
                    f"the board image is built for D in {BOARD_DECIMATIONS}, not {decimation}"
                )
            elf = build_board() / f"fd_board_d{decimation}.elf"
        self._check_scales(mp)
        self.ts = float(mp[pl.MP_TS])
        self.decimation = int(decimation)
        self.cmd_timeout_s = cmd_timeout_s
        self.elf = elf
        self._uc_mod, self._ac = uc, ac
        data, segs, syms = read_elf(elf)
        self.syms = syms
        self.mu = mu = uc.Uc(uc.UC_ARCH_ARM, uc.UC_MODE_THUMB | uc.UC_MODE_MCLASS)
        mu.ctl_set_cpu_model(ac.UC_CPU_ARM_CORTEX_M4)
        # the flash: the image's part as memory, the storage pages through the FLASH
        # interface's model (reads of the array, writes as programming steps)
        mu.mem_map(_FLASH, _STORE - _FLASH, uc.UC_PROT_READ | uc.UC_PROT_EXEC)
        mu.mem_map(_RAM, _RAM_SIZE)
        mu.mem_map(_CCM, _CCM_SIZE)
        mu.mem_map(rm.SRAMCAN_BASE & ~0xFFF, 0x1000)
        if flash_image is not None and len(flash_image) != _FLASH_SIZE:
            raise ValueError(f"a flash image has {_FLASH_SIZE} bytes, not {len(flash_image)}")
        self.flash = bytearray(b"\xff" * _FLASH_SIZE if flash_image is None else flash_image)
        for paddr, off, size in segs:
            if paddr + size > _STORE:
                raise ValueError(f"{elf.name} reaches into the parameter pages at {_STORE:#x}")
            self.flash[paddr - _FLASH : paddr - _FLASH + size] = data[off : off + size]
        mu.mem_write(_FLASH, bytes(self.flash[: _STORE - _FLASH]))
        mu.mmio_map(_STORE, _STORE_SIZE, self._flash_read, None, self._flash_write, None)
        self._init_regs()
        for page in _PAGES:
            mu.mmio_map(page, 0x1000, self._read, page, self._write, page)
        self.counting = False
        self._n = 0
        self._block_n: dict[tuple[int, int], int] = {}
        self.isr_instructions: list[int] = []
        self.trace = trace and measure
        self.isr_blocks: list[collections.Counter[tuple[int, int]]] = []
        """trace=True: per period interrupt, how often each translated block (address,
        size) ran; with :attr:`flash` the executed instruction stream, for a cycle model."""
        self._blocks: collections.Counter[tuple[int, int]] = collections.Counter()
        self.measure = measure
        self.on_isr: Any = None
        """Called after each period interrupt with (instructions, executed blocks in order
        [(address, size)]) when set (and ``measure``): a cycle model's input."""
        self.bg_instructions: list[int] = []
        """Instructions of each pass of the background loop (from its idle point round to
        it again: the CAN frames received handed to the core, the IWDG refresh)."""
        self.on_background: Any = None
        """As :attr:`on_isr`, after each pass of the background loop."""
        self._seq: list[tuple[int, int]] = []
        if measure:
            mu.hook_add(uc.UC_HOOK_BLOCK, self._on_block, begin=_FLASH, end=_FLASH + 0x80000)
            mu.hook_add(uc.UC_HOOK_BLOCK, self._on_block, begin=_CCM, end=_CCM + _CCM_SIZE)
        self._init_models()
        self._proto = get_protocol()
        self._boot()

    def _init_models(self) -> None:
        """The plant-side state of the peripheral models, at reset."""
        self._adc = [ADC_MID, ADC_MID, ADC_MID, 0]
        self._temp_counts = TEMP_ZERO_COUNTS + 35 * TEMP_COUNTS_PER_C
        self._pulses = [(0, 0), (0, 0), (0, 0)]  # per line: (+ width, - width) [ticks]
        self._encoder = 0
        self._time_us = 0
        self._i_peak_counts = 0
        self._shadow = [TIM1_ARR] * 3
        self._rx_wait: collections.deque[can.Message] = collections.deque()
        self._rx_fifo: collections.deque[tuple[int, int, bytes]] = collections.deque()
        self._rx_get = 0
        self._tx_put = 0
        self._tx: list[can.Message] = []
        self.iwdg_refreshes = 0
        self.iwdg_resets = 0
        self._iwdg_k = 0
        self.break_trips = 0
        self.gate_fault = False
        self._overrun_next = False
        self._adc_held: dict[int, int] = {}
        self._period_irq = False  # the period interrupt is running
        self.periods = 0
        self._flash_first: tuple[int, int] | None = None  # a double-word's first word
        self._flash_key_state = 0  # KEYR: 0 KEY1 next, 1 KEY2 next, -1 locked until reset
        self.flash_operations = 0
        """Page erases and double-word programs started (the storage's writes)."""
        self._power_ops: int | None = None

    # ------------------------------------------------------------------ set-up
    @staticmethod
    def _check_scales(mp: np.ndarray) -> None:
        s = sensor_scales(mp)
        want = {"current_lsb_a": 40.0 / 4096.0, "current_mid_counts": ADC_MID,
                "vdc_lsb_v": 100.0 / 4096.0}  # fmt: skip
        for k, v in want.items():
            got = getattr(s, k)
            if abs(got - v) > 1e-12 * max(1.0, abs(v)):
                raise ValueError(
                    f"the plant's {k} is {got:g}, the board image's {v:g} (fd_board.h)"
                )

    def _init_regs(self) -> None:
        self.regs: dict[int, int] = {addr: reset for addr, reset in rm.REG.values()}
        self._r = {n: _reg(n) for n in rm.REG}

    def _boot(self) -> None:
        """Reset: SP and PC from the vector table, run until the background loop idles."""
        ac = self._ac
        sp, pc = struct.unpack_from("<II", self.flash, 0)
        self.vectors = struct.unpack_from(f"<{16 + max(rm.IRQ.values()) + 1}I", self.flash, 0)
        self._wait = self.syms["fd_board_wait"][0] & ~1
        mu = self.mu
        mu.reg_write(ac.UC_ARM_REG_SP, sp)
        self.stack_top = sp
        self.stack_bottom = sp - self.syms["_stack_size"][0]
        mu.emu_start(pc | 1, self._wait, count=50_000_000)
        self._main = mu.context_save()
        dbg = self.syms["fd_board_debug"][0]
        names = ("size", "k", "armed", "pwm_enabled", "fault_latched", "split", "fault_code",
                 "mode", "stats", "prm", "ref_box", "cmds", "cmd_size", "cmd_slots",
                 "ref_box_taken", "cmd_ring", "cmd_ring_slots", "board_size",
                 "next_status_k", "next_fault_k", "last_cmd_k", "last_ref_k",
                 "ran_first")  # fmt: skip
        vals = struct.unpack(f"<{len(names)}I", mu.mem_read(dbg, 4 * len(names)))
        self._off = dict(zip(names, vals, strict=True))
        self._core = self.syms["fd_board_core"][0]
        if self.mu.mem_read(_CPACR, 4) == b"":  # pragma: no cover - mapped above
            raise RuntimeError("SCS not mapped")

    # ------------------------------------------------------------------ MMIO
    def _read(self, mu: Any, offset: int, size: int, page: int) -> int:
        addr = page + offset
        a4 = addr & ~3
        v = self._special_read(a4)
        if v is None:
            v = self.regs.get(a4, 0)
        return (v >> (8 * (addr & 3))) & ((1 << (8 * size)) - 1)

    def _write(self, mu: Any, offset: int, size: int, value: int, page: int) -> None:
        addr = page + offset
        a4 = addr & ~3
        if size < 4:  # byte/halfword store (NVIC priorities): merge
            shift = 8 * (addr & 3)
            mask = ((1 << (8 * size)) - 1) << shift
            value = (self.regs.get(a4, 0) & ~mask) | ((value << shift) & mask)
        self._special_write(a4, value & 0xFFFFFFFF)

    def _special_read(self, a: int) -> int | None:
        r = self._r
        if a == r["TIM2_CNT"]:
            return self._time_us & 0xFFFFFFFF
        if a == r["TIM4_CNT"]:
            return self._encoder & 0xFFFF
        if a == r["FDCAN1_RXF0S"]:
            n = len(self._rx_fifo)
            return n | (self._rx_get << 8) | (((self._rx_get + n) % 3) << 16) | ((n == 3) << 24)
        if a == r["FDCAN1_TXFQS"]:
            return 3 | (self._tx_put << 16)  # the model sends at once: always 3 free
        if a == r["IWDG_SR"]:
            return 0
        if a == r["GPIOC_IDR"]:  # nFAULT (PC10, pulled up): low while a gate fault is on
            return 0 if self.gate_fault else 1 << 10
        return None

    def _special_write(self, a: int, v: int) -> None:
        r, regs = self._r, self.regs
        if a == r["RCC_CR"]:  # oscillators and the PLL are ready at once
            for on, rdy in (("HSION", "HSIRDY"), ("HSEON", "HSERDY"), ("PLLON", "PLLRDY")):
                v = (
                    v | _bit(f"RCC_CR_{rdy}")
                    if v & _bit(f"RCC_CR_{on}")
                    else v & ~_bit(f"RCC_CR_{rdy}")
                )
        elif a == r["RCC_CFGR"]:  # the switch is immediate: SWS follows SW
            sw = v & _bit("RCC_CFGR_SW")
            v = (v & ~_bit("RCC_CFGR_SWS")) | (sw << rm.FIELD["RCC_CFGR_SWS"][0])
        elif a in (r["ADC1_CR"], r["ADC2_CR"]):
            isr = a - r["ADC1_CR"] + r["ADC1_ISR"]
            v &= ~_bit("ADC1_CR_ADCAL")  # calibration done at once
            if v & _bit("ADC1_CR_ADEN"):
                regs[isr] = regs.get(isr, 0) | _bit("ADC1_ISR_ADRDY")
        elif a in (r["ADC1_ISR"], r["ADC2_ISR"], r["FDCAN1_IR"], r["FLASH_SR"]):  # rc_w1
            v = regs.get(a, 0) & ~v
        elif a == r["FLASH_KEYR"]:  # write-only
            self._flash_key(v)
            return
        elif a == r["FLASH_CR"]:
            v = self._flash_cr(v)
        elif a in (r["TIM1_SR"], r["TIM3_SR"], r["TIM5_SR"], r["TIM8_SR"]):  # rc_w0
            v = regs.get(a, 0) & v
            if a == r["TIM1_SR"] and self._overrun_next and self._period_irq:
                # an injected overrun: the next update event falls inside this interrupt
                v |= _bit("TIM1_SR_UIF")
                self._overrun_next = False
        elif a == r["TIM1_EGR"]:
            if v & 1:  # UG: shadows loaded
                self._shadow = [regs[r[f"TIM1_CCR{j}"]] for j in (1, 2, 3)]
            v = 0
        elif a == r["FDCAN1_TXBAR"]:
            self._transmit(v)
            v = 0
        elif a == r["FDCAN1_RXF0A"]:
            if self._rx_fifo:
                self._rx_fifo.popleft()
                self._rx_get = (self._rx_get + 1) % 3
                self._refill()
        elif a == r["IWDG_KR"] and v == 0xAAAA:
            self.iwdg_refreshes += 1
            self._iwdg_k = self.periods
        elif _NVIC_ISER0 <= a < _NVIC_ISER0 + 32:  # write 1 to set
            v |= regs.get(a, 0)
        elif a == r["GPIOC_BSRR"]:
            odr = r["GPIOC_ODR"]
            regs[odr] = (regs.get(odr, 0) | (v & 0xFFFF)) & ~(v >> 16)
            return
        regs[a] = v

    # ------------------------------------------------------------------ FLASH
    def _flash_read(self, mu: Any, offset: int, size: int, user: Any) -> int:
        """A read of the storage pages (the flash's content, little-endian)."""
        a = _STORE - _FLASH + offset
        return int.from_bytes(self.flash[a : a + size], "little")

    def _flash_write(self, mu: Any, offset: int, size: int, value: int, user: Any) -> None:
        """A write to the storage pages: a programming step (RM0440 3.3.7): with PG set,
        a word at an 8-byte aligned address and the next word at +4 program that
        double-word, if it is erased (else PROGERR, unless both words are 0)."""
        r, regs = self._r, self.regs
        sr, cr = r["FLASH_SR"], regs[r["FLASH_CR"]]
        addr = _STORE + offset
        pending = (
            _bit("FLASH_SR_PROGERR") | _bit("FLASH_SR_SIZERR") | _bit("FLASH_SR_PGAERR")
            | _bit("FLASH_SR_WRPERR") | _bit("FLASH_SR_MISERR") | _bit("FLASH_SR_FASTERR")
        )  # fmt: skip
        err = 0
        if not cr & _bit("FLASH_CR_PG") or regs[sr] & pending:
            err = _bit("FLASH_SR_PGSERR")
        elif size != 4:
            err = _bit("FLASH_SR_SIZERR")
        elif self._flash_first is None:
            if addr % 8:
                err = _bit("FLASH_SR_PGAERR")
            else:
                self._flash_first = (addr, value & 0xFFFFFFFF)
                return
        else:
            first, lo = self._flash_first
            self._flash_first = None
            if addr != first + 4:
                err = _bit("FLASH_SR_PGAERR")
            else:
                a = first - _FLASH
                old = self.flash[a : a + 8]
                new = struct.pack("<II", lo, value & 0xFFFFFFFF)
                if old != b"\xff" * 8 and new != bytes(8):
                    err = _bit("FLASH_SR_PROGERR")
                elif self._flash_operation():
                    self.flash[a : a + 8] = new
        self._flash_done(err)

    def _flash_operation(self) -> bool:
        """An erase or a double-word program starts: counted; False once the power is
        cut (:meth:`cut_power_after`): the flash keeps what it holds."""
        self.flash_operations += 1
        return self._power_ops is None or self.flash_operations <= self._power_ops

    def _flash_done(self, err: int) -> None:
        """The end of an operation: its error flags, EOP if EOPIE (RM0440 3.7.5); the
        model's operations take no time (BSY never reads set)."""
        r, regs = self._r, self.regs
        eop = _bit("FLASH_SR_EOP") if regs[r["FLASH_CR"]] & _bit("FLASH_CR_EOPIE") else 0
        regs[r["FLASH_SR"]] |= err or eop

    def _flash_cr(self, v: int) -> int:
        """FLASH_CR written: ignored while LOCK is set (only LOCK may be set again); STRT
        with PER erases page PNB of bank BKER (2 KB pages, dual bank). Only the storage
        pages are writable in the model: elsewhere WRPERR, as if write-protected."""
        r, regs = self._r, self.regs
        cr = regs[r["FLASH_CR"]]
        if cr & _bit("FLASH_CR_LOCK"):
            return cr
        if not v & _bit("FLASH_CR_STRT"):
            return v
        v &= ~_bit("FLASH_CR_STRT")  # cleared by hardware at the operation's end
        if v & (_bit("FLASH_CR_MER1") | _bit("FLASH_CR_MER2")):
            self._flash_done(_bit("FLASH_SR_WRPERR"))
        elif v & _bit("FLASH_CR_PER"):
            pos, _w = rm.FIELD["FLASH_CR_PNB"]
            pnb = (v & _bit("FLASH_CR_PNB")) >> pos
            bank = 1 if v & _bit("FLASH_CR_BKER") else 0
            a = bank * _BANK_BYTES + pnb * _PAGE_BYTES
            if not _STORE - _FLASH <= a < _STORE - _FLASH + _STORE_SIZE:
                self._flash_done(_bit("FLASH_SR_WRPERR"))
            else:
                if self._flash_operation():
                    self.flash[a : a + _PAGE_BYTES] = b"\xff" * _PAGE_BYTES
                self._flash_done(0)
        return v

    def _flash_key(self, v: int) -> None:
        """FLASH_KEYR: KEY1 then KEY2 clears LOCK; any other sequence locks FLASH_CR until
        the next reset (RM0440 3.3.5; the bus error it raises is not modelled)."""
        r, regs = self._r, self.regs
        if self._flash_key_state == 0 and v == _FLASH_KEY1:
            self._flash_key_state = 1
        elif self._flash_key_state == 1 and v == _FLASH_KEY2:
            self._flash_key_state = 0
            regs[r["FLASH_CR"]] &= ~_bit("FLASH_CR_LOCK")
        else:
            self._flash_key_state = -1  # locked until reset

    def storage_note(self) -> str:
        """Where the parameters the board booted with came from, in words (its
        fd_board.store_state and the core's PARAM_SOURCE)."""
        st = self.board_state()
        if st["store_state"] == 1:
            return f"the stored set {st['store_seq']} (flash, CRC good)"
        if st["store_state"] == 2:
            return (
                "the defaults: the flash holds parameter pages but no intact set (bad CRC; "
                f"PARAM_SOURCE {self.param_read('PARAM_SOURCE'):g})"
            )
        return "the defaults (nothing stored in flash)"

    def flash_image(self) -> bytes:
        """The flash as it is now (the image and the parameter pages): a new board from
        it (``VirtualBoard(..., flash_image=...)``) is this one after a power cycle."""
        return bytes(self.flash)

    def cut_power_after(self, operations: int | None) -> None:
        """From now on, the flash operations (page erases, double-word programs) after the
        first ``operations`` do not happen, as if the supply went at that point: what
        the flash then holds (:meth:`flash_image`) is what the next boot finds. None:
        powered again."""
        self._power_ops = None if operations is None else self.flash_operations + operations

    # ------------------------------------------------------------------ FDCAN
    def _transmit(self, bits: int) -> None:
        for idx in range(3):
            if not bits & (1 << idx):
                continue
            base = rm.SRAMCAN_BASE + _MRAM_TXB + idx * _MRAM_ELEM
            t0, t1 = struct.unpack("<II", self.mu.mem_read(base, 8))
            n = _DLC_LEN[(t1 >> 16) & 0xF]
            fd = bool(t1 & (1 << 21))
            self._tx.append(
                can.Message(
                    arbitration_id=(t0 >> 18) & 0x7FF,
                    is_extended_id=False,
                    is_fd=fd,
                    bitrate_switch=bool(t1 & (1 << 20)),
                    data=bytes(self.mu.mem_read(base + 8, n)),
                )
            )
            self._tx_put = (idx + 1) % 3

    def _accepts(self, aid: int) -> bool:
        """The standard-id filter elements the firmware wrote (classic id/mask, FIFO 0)."""
        lss = (self.regs.get(self._r["FDCAN1_RXGFC"], 0) >> rm.FIELD["FDCAN1_RXGFC_LSS"][0]) & 0x1F
        words = struct.unpack(f"<{lss}I", self.mu.mem_read(rm.SRAMCAN_BASE, 4 * lss))
        for w in words:
            sft, sfec, id1, id2 = w >> 30, (w >> 27) & 7, (w >> 16) & 0x7FF, w & 0x7FF
            if sft == 2 and sfec == 1 and (aid & id2) == (id1 & id2):
                return True
        return False

    def _refill(self) -> None:
        """Frames waiting on the bus side into free RX FIFO 0 elements."""
        while self._rx_wait and len(self._rx_fifo) < 3:
            msg = self._rx_wait.popleft()
            idx = (self._rx_get + len(self._rx_fifo)) % 3
            data = bytes(msg.data)[:64]
            dlc = next(i for i, n in enumerate(_DLC_LEN) if n >= len(data))
            base = rm.SRAMCAN_BASE + _MRAM_RF0 + idx * _MRAM_ELEM
            r0 = (msg.arbitration_id & 0x7FF) << 18
            r1 = (
                (dlc << 16)
                | ((1 << 21) if msg.is_fd else 0)
                | ((1 << 20) if msg.bitrate_switch else 0)
            )
            self.mu.mem_write(base, struct.pack("<II", r0, r1) + data.ljust(64, b"\0"))
            self._rx_fifo.append((msg.arbitration_id, dlc, data))

    # ------------------------------------------------------------------ calls
    def _call(self, fn: str, args: tuple[int, ...] = (), fargs: tuple[float, ...] = ()) -> int:
        """Call a firmware function from the background context (between interrupts)."""
        ac, mu = self._ac, self.mu
        mu.context_restore(self._main)
        sp = (mu.reg_read(ac.UC_ARM_REG_SP) - EXC_FRAME_BYTES - 64) & ~7
        for i, a in enumerate(args):
            mu.reg_write(ac.UC_ARM_REG_R0 + i, a & 0xFFFFFFFF)
        for i, f in enumerate(fargs):
            mu.reg_write(ac.UC_ARM_REG_S0 + i, struct.unpack("<I", struct.pack("<f", f))[0])
        mu.reg_write(ac.UC_ARM_REG_SP, sp)
        mu.reg_write(ac.UC_ARM_REG_LR, _RETURN | 1)
        mu.emu_start(self.syms[fn][0] | 1, _RETURN, count=5_000_000)
        out = mu.reg_read(ac.UC_ARM_REG_R0)
        mu.context_restore(self._main)
        return int(out)

    def _interrupt(self, irq: int) -> None:
        """Exception entry for device line ``irq`` (if the NVIC enables it): the frame
        stacked below the background loop's SP, the handler run until it returns."""
        ac, mu = self._ac, self.mu
        iser = self.regs.get(_NVIC_ISER0 + 4 * (irq >> 5), 0)
        if not iser & (1 << (irq & 31)):
            return
        mu.context_restore(self._main)
        sp = mu.reg_read(ac.UC_ARM_REG_SP)
        frame_sp = (sp - EXC_FRAME_BYTES) & ~7
        regs = [mu.reg_read(ac.UC_ARM_REG_R0 + i) for i in range(4)]
        regs += [mu.reg_read(ac.UC_ARM_REG_R12), mu.reg_read(ac.UC_ARM_REG_LR),
                 mu.reg_read(ac.UC_ARM_REG_PC), 0x01000000]  # fmt: skip
        mu.mem_write(frame_sp, struct.pack("<8I", *regs) + bytes(EXC_FRAME_BYTES - 32))
        mu.reg_write(ac.UC_ARM_REG_SP, frame_sp)
        mu.reg_write(ac.UC_ARM_REG_LR, _RETURN | 1)
        self._n = 0
        self._blocks = collections.Counter()
        self._seq = []
        self.counting = self.measure
        self._period_irq = irq == rm.IRQ["ADC1_2"]
        mu.emu_start(self.vectors[16 + irq] | 1, _RETURN, count=5_000_000)
        self.counting = self._period_irq = False
        if self.measure and irq == rm.IRQ["ADC1_2"]:
            self.isr_instructions.append(self._n)
            if self.trace:
                self.isr_blocks.append(self._blocks)
            if self.on_isr is not None:
                self.on_isr(self._n, self._seq)
        mu.context_restore(self._main)

    def _background(self) -> None:
        """The background loop from its idle point once round to it again (measured: its
        instructions into :attr:`bg_instructions`, :attr:`on_background` called)."""
        mu = self.mu
        mu.context_restore(self._main)
        self._n = 0
        self._seq = []
        self._blocks = collections.Counter()  # not the last interrupt's (isr_blocks)
        self.counting = self.measure
        mu.emu_start((self._wait + 2) | 1, self._wait, count=5_000_000)
        self.counting = False
        self._main = mu.context_save()
        if self.measure:
            self.bg_instructions.append(self._n)
            if self.on_background is not None:
                self.on_background(self._n, self._seq)

    def _on_block(self, mu: Any, address: int, size: int, user: Any) -> None:
        if self.counting:
            key = (address, size)
            n = self._block_n.get(key)
            if n is None:
                code = bytes(mu.mem_read(address, size))
                n = self._block_n[key] = _thumb_count(code)
            self._n += n
            if self.trace:
                self._blocks[key] += 1
            if self.on_isr is not None or self.on_background is not None:
                self._seq.append(key)

    # ------------------------------------------------------------------ the interface
    def param_write(self, name: str | int, value: float) -> str:
        pid = PARAM_IDS[name] if isinstance(name, str) else int(name)
        return PA_CHOICES[self._call("fd_core_param_write", (self._core, pid), (float(value),))]

    def param_read(self, name: str | int) -> float:
        """The value in effect (fd_core_param_read: a board limit where it is stricter)."""
        pid = PARAM_IDS[name] if isinstance(name, str) else int(name)
        self._call("fd_core_param_read", (self._core, pid, _SCRATCH))
        return float(struct.unpack("<f", self.mu.mem_read(_SCRATCH, 4))[0])

    def inject(
        self,
        *,
        gate_fault: bool = False,
        can_tec: int = 0,
        can_rec: int = 0,
        can_bus_off: bool = False,
        overrun: bool = False,
    ) -> None:
        """FirmwareCore.inject on the board's inputs: nFAULT (PC10) low, FDCAN1's error
        counters (ECR) and bus-off (PSR.BO; held until the next call), and the next period
        interrupt overrunning (TIM1's update flag set again while it runs)."""
        r = self._r
        self.gate_fault = bool(gate_fault)
        tec_pos, rec_pos = rm.FIELD["FDCAN1_ECR_TEC"][0], rm.FIELD["FDCAN1_ECR_REC"][0]
        self.regs[r["FDCAN1_ECR"]] = (min(can_tec, 255) << tec_pos) | (min(can_rec, 127) << rec_pos)
        psr = self.regs.get(r["FDCAN1_PSR"], 0) & ~_bit("FDCAN1_PSR_BO")
        self.regs[r["FDCAN1_PSR"]] = psr | (_bit("FDCAN1_PSR_BO") if can_bus_off else 0)
        self._overrun_next = bool(overrun)

    def hold_adc(self, phase: int, counts: int | None) -> None:
        """FirmwareCore.hold_adc: ADC1's injected result of `phase` held at `counts` (a
        converter fault; COMP1 still sees the current); None releases it."""
        if counts is None:
            self._adc_held.pop(phase, None)
        else:
            self._adc_held[phase] = int(counts)

    def set_break(self, threshold_a: float) -> None:
        """FirmwareCore.set_break: on the board the image sets its comparator (DAC3 at
        FD_BOARD_HW_OVERCURRENT_A); the threshold must be that one (0: it stays)."""
        if threshold_a == 0.0:
            return
        dac = self.regs.get(self._r["DAC3_DHR12R1"], 4095) - ADC_MID
        if abs(dac * 40.0 / 4096.0 - threshold_a) > 40.0 / 4096.0:
            raise ValueError(
                f"the board image's comparator is at {dac * 40.0 / 4096.0:.2f} A, "
                f"not {threshold_a:g} A"
            )

    def set_sample(self, frame: np.ndarray, time_us: int, temp_c: int = 35) -> None:
        """Sample k: the analog inputs at t_k and the comparator pulses of the period just
        ended, for the next :meth:`period`."""
        lsb = 40.0 / 4096.0
        cur = [int(round(frame[pl.FR_IA + j] / lsb)) + ADC_MID for j in range(3)]
        vdc = float(frame[pl.FR_VDC])
        self._adc = [*cur, int(round(vdc / (100.0 / 4096.0)))]
        self._i_peak_counts = max(abs(c - ADC_MID) for c in cur)  # COMP1: the analog side
        for j, counts in self._adc_held.items():
            self._adc[j] = counts
        self._temp_counts = TEMP_ZERO_COUNTS + int(temp_c) * TEMP_COUNTS_PER_C
        for j in range(3):
            frac = float(frame[pl.FR_VAB + j]) / vdc if vdc > 0.0 else 0.0
            w = int(round(abs(frac) * CAPTURE_TICKS))
            self._pulses[j] = (w, 0) if frac > 0 else (0, w)
        self._encoder = int(frame[pl.FR_ENC])
        self._time_us = int(time_us)

    def set_time(self, time_us: int) -> None:
        self._time_us = int(time_us)

    def _update_event(self) -> None:
        """TIM1's update at the valley: compare shadows, TRGO to the ADCs and capture
        timers, the over-current comparator and break."""
        regs, r = self.regs, self._r
        if not regs.get(r["TIM1_CR1"], 0) & 1:
            return
        self._shadow = [regs.get(r[f"TIM1_CCR{j}"], 0) for j in (1, 2, 3)]
        regs[r["TIM1_SR"]] = regs.get(r["TIM1_SR"], 0) | _bit("TIM1_SR_UIF")
        for j, tim in enumerate(("TIM3", "TIM5", "TIM8")):
            pos, neg = self._pulses[j]
            sr = 0
            centre = CAPTURE_TICKS // 2
            if pos > 0:
                regs[r[f"{tim}_CCR1"]] = centre - pos // 2
                regs[r[f"{tim}_CCR2"]] = centre - pos // 2 + pos
                sr |= 0b110
            if neg > 0:
                regs[r[f"{tim}_CCR3"]] = centre - neg // 2
                regs[r[f"{tim}_CCR4"]] = centre - neg // 2 + neg
                sr |= 0b11000
            regs[r[f"{tim}_SR"]] = sr
        # COMP1 (+: the bus current, modelled as the largest phase current) vs DAC3 CH1
        thr = regs.get(r["DAC3_DHR12R1"], 4095) - ADC_MID
        comp_on = bool(regs.get(r["COMP_C1CSR"], 0) & _bit("COMP_C1CSR_EN"))
        high = comp_on and self._i_peak_counts >= thr
        csr = regs.get(r["COMP_C1CSR"], 0) & ~_bit("COMP_C1CSR_VALUE")
        regs[r["COMP_C1CSR"]] = csr | (_bit("COMP_C1CSR_VALUE") if high else 0)
        bdtr = regs.get(r["TIM1_BDTR"], 0)
        if (
            high
            and bdtr & _bit("TIM1_BDTR_BKE")
            and regs.get(r["TIM1_AF1"], 0) & _bit("TIM1_AF1_BKCMP1E")
        ):
            regs[r["TIM1_BDTR"]] = bdtr & ~_bit("TIM1_BDTR_MOE")
            regs[r["TIM1_SR"]] = regs.get(r["TIM1_SR"], 0) | _bit("TIM1_SR_BIF")
            self.break_trips += 1
            if regs.get(r["TIM1_DIER"], 0) & _bit("TIM1_DIER_BIE"):
                self._interrupt(rm.IRQ["TIM1_BRK_TIM15"])
        # injected conversions (TRGO, rising edge) of both ADCs
        for adc, vals in (("ADC1", self._adc), ("ADC2", [self._temp_counts])):
            if not regs.get(r[f"{adc}_CR"], 0) & _bit("ADC1_CR_JADSTART"):
                continue
            for i, v in enumerate(vals):
                regs[r[f"{adc}_JDR{i + 1}"]] = min(max(v, 0), 4095)
            regs[r[f"{adc}_ISR"]] = (
                regs.get(r[f"{adc}_ISR"], 0) | _bit("ADC1_ISR_JEOS") | _bit("ADC1_ISR_JEOC")
            )

    def period(self) -> None:
        """One PWM period from the valley t_k: update event, conversions, the period
        interrupt, the background loop. Frames received since the last period woke the
        background loop first (the FDCAN's new-message interrupt ends its wfi): the core
        takes CAN frames only there and hands commands and references to the interrupt."""
        waiting = len(self._rx_fifo) + len(self._rx_wait)
        while waiting:
            self._background()
            left = len(self._rx_fifo) + len(self._rx_wait)
            if left >= waiting:
                break
            waiting = left
        self._update_event()
        r = self._r
        if self.regs.get(r["ADC1_IER"], 0) & _bit("ADC1_IER_JEOSIE") and self.regs.get(
            r["ADC1_ISR"], 0
        ) & _bit("ADC1_ISR_JEOS"):
            self._interrupt(rm.IRQ["ADC1_2"])
        self.periods += 1
        self._background()
        if self.periods - self._iwdg_k > IWDG_PERIODS:
            self.iwdg_resets += 1
            self._iwdg_k = self.periods

    def pwm(self) -> tuple[np.ndarray, bool]:
        """Duties and outputs over [t_k, t_(k+1)]: the active (shadow) compare values in
        PWM mode 2 (high side on while CNT > CCR) and MOE."""
        moe = bool(self.regs.get(self._r["TIM1_BDTR"], 0) & _bit("TIM1_BDTR_MOE"))
        d = np.array([(TIM1_ARR - min(c, TIM1_ARR)) / TIM1_ARR for c in self._shadow])
        return d, moe

    def push(self, msg: can.Message) -> bool:
        """A frame from the bus: dropped by the filters, or into RX FIFO 0; while the
        FIFO's 3 elements are taken it waits on the bus side (the sender's queue) and
        enters as the core releases elements (RXF0A). Always True."""
        if msg.is_extended_id or not self._accepts(msg.arbitration_id):
            return True
        self._rx_wait.append(msg)
        self._refill()
        return True

    def handle_now(self, msg: can.Message) -> None:
        """Hand a frame to the core between interrupts (fd_core_handle_frame from the
        background context); its answer is in :meth:`pop_tx`."""
        data = bytes(msg.data)[:64]
        frame = struct.pack("<IBB", msg.arbitration_id, len(data), int(bool(msg.is_fd)))
        self.mu.mem_write(_SCRATCH, frame + data.ljust(64, b"\0") + b"\0\0")
        self._call("fd_core_handle_frame", (self._core, _SCRATCH))

    def pop_tx(self) -> list[can.Message]:
        out, self._tx = self._tx, []
        return out

    def has_answer(self, seq: int) -> bool:
        """The host's answer to sample ``seq`` taken in by the core (fd_core_has_answer's
        test on the core's memory) or waiting in RX FIFO 0."""
        seq &= 0xFFFF
        o, mem = self._off, self.mu.mem_read
        if self.state()["split"]:
            # the sequence-locked reference: even, not yet taken, answering seq
            box, s, valid = struct.unpack("<IHB", mem(self._core + o["ref_box"], 7))
            (taken,) = struct.unpack("<I", mem(self._core + o["ref_box_taken"], 4))
            if box != taken and not box & 1 and valid and s == seq:
                return True
        else:
            raw = mem(self._core + o["cmds"], o["cmd_size"] * o["cmd_slots"])
            for i in range(o["cmd_slots"]):
                s, valid = struct.unpack_from("<HB", raw, i * o["cmd_size"])
                if valid and s == seq:
                    return True
            # the ring the background fills: slots, then head, then tail
            n = o["cmd_ring_slots"]
            ring = mem(self._core + o["cmd_ring"], o["cmd_size"] * n + 8)
            head, tail = struct.unpack_from("<II", ring, o["cmd_size"] * n)
            for i in range(tail, head):
                s, _valid = struct.unpack_from("<HB", ring, (i % n) * o["cmd_size"])
                if s == seq:
                    return True
        waiting = [(m.arbitration_id, 0, bytes(m.data)) for m in self._rx_wait]
        for aid, _dlc, data in [*self._rx_fifo, *waiting]:
            if aid in (ID_DUTY_CMD, ID_HOST_REF):
                name, key = (
                    ("DUTY_CMD", "cmd_seq") if aid == ID_DUTY_CMD else ("HOST_REF", "ref_seq")
                )
                if int(self._proto.message(name).decode(data, decode_choices=False)[key]) == seq:
                    return True
        return False

    # ------------------------------------------------------------------ state
    def _u8(self, field: str) -> int:
        return self.mu.mem_read(self._core + self._off[field], 1)[0]

    @property
    def k(self) -> int:
        return int(struct.unpack("<I", self.mu.mem_read(self._core + self._off["k"], 4))[0])

    def restart_period_index(self) -> None:
        """The lockstep bench's run origin: the core's period counter back to 0, what it
        schedules moved with it, the next boundary the first again (as
        ``fd_sil_restart_period_index`` on the SIL build)."""
        k = self.k
        for name in ("k", "next_status_k", "next_fault_k", "last_cmd_k", "last_ref_k"):
            addr = self._core + self._off[name]
            (v,) = struct.unpack("<I", self.mu.mem_read(addr, 4))
            self.mu.mem_write(addr, struct.pack("<I", (v - k) & 0xFFFFFFFF))
        self.mu.mem_write(self._core + self._off["ran_first"], b"\0")

    def state(self) -> dict[str, int | bool]:
        return {
            "armed": bool(self._u8("armed")),
            "pwm_enabled": bool(self._u8("pwm_enabled")),
            "fault_latched": bool(self._u8("fault_latched")),
            "split": bool(self._u8("split")),
            "fault_code": self._u8("fault_code"),
            "mode": self._u8("mode") & 0xF,
        }

    def stats(self) -> dict[str, int]:
        raw = self.mu.mem_read(self._core + self._off["stats"], 4 * len(_STAT_NAMES))
        return dict(zip(_STAT_NAMES, struct.unpack(f"<{len(_STAT_NAMES)}I", raw), strict=True))

    def stack_high_water(self) -> int:
        """Bytes of the main stack ever used (the painted words overwritten)."""
        n = (self.stack_top - self.stack_bottom) // 4
        words = struct.unpack(f"<{n}I", self.mu.mem_read(self.stack_bottom, 4 * n))
        for i, w in enumerate(words):
            if w != STACK_PAINT:
                return self.stack_top - (self.stack_bottom + 4 * i)
        return 0

    def board_state(self) -> dict[str, int]:
        """fd_board_t's counters and the parameter storage's state (store_state: 0 nothing
        stored, 1 an intact set, store_seq its number, 2 pages written and none intact)."""
        names = ("periods", "break_trips", "bus_off_events", "rx_lost", "clock_source",
                 "store_state", "store_seq", "store_saves", "store_errors",
                 "store_error_sr")  # fmt: skip
        raw = self.mu.mem_read(self.syms["fd_board"][0], 4 * len(names))
        return dict(zip(names, struct.unpack(f"<{len(names)}I", raw), strict=True))
