"""Cycle bounds of executed Cortex-M4F code: the cost model of ``benchmark firmware``.

QEMU counts instructions, not cycles. This module costs every executed instruction of a
trace (the program counters QEMU logged) with the Cortex-M4 and FPv4-SP timings of ARM's
technical reference manuals, giving a lower and an upper bound per interrupt:

================================  ===========  ===========
instruction class                 lower        upper
================================  ===========  ===========
integer ALU, move, compare, IT    1            1
MUL / MLA, MLS                    1 / 2        1 / 2
UDIV, SDIV                        2            12
LDR/STR (any width), VLDR/VSTR    1 after a    2
                                  single load/
                                  store, else 2
LDRD/STRD                         3            3
LDM/STM/PUSH/POP, VLDM/VSTM,      1 + N        1 + N
VPUSH/VPOP (N registers, a D
register counts 2)
branch not taken                  1            1
branch taken (B, BL, BX, CBZ,     2            4
POP {pc}, anything writing pc)    (1 + P, P = 1..3: pipeline refill; TBB/TBH 2 + P)
FPU add/sub/mul/neg/abs/cmp/cvt,  1            1
VMOV, VMRS
VMOV of two core registers        2            2
VMLA/VMLS/VFMA/VFMS/VNMLA/...     3            3
VDIV, VSQRT                       14           14
================================  ===========  ===========

Where the code runs from (the G474 image's placement of each executed function, read from
its symbol table):

- **CCM SRAM** (0x1000_0000, zero wait states on the I-bus): nothing added to the lower
  bound; the upper bound adds 1 cycle per PC-relative (literal-pool) load, which meets the
  instruction fetch on the same single-ported memory.
- **flash** (4 wait states at 170 MHz behind the ART accelerator): nothing added to the lower
  bound (every fetch hits the ART cache); the upper bound assumes every fetch misses it
  (the interrupt executes several KB, its cache holds 1 KB): a straight run of instructions
  costs the larger of its execution cycles and its 64-bit line fetches (5 cycles each, the
  prefetch overlapping them with execution), each taken branch into flash 4 wait states
  more, each literal-pool load 4 more.

Interrupt entry and exit: 12 cycles each in both bounds; the upper bound adds the lazy
stacking of the FP context (S0-S15 and FPSCR, 17 words each way) for an interrupted
context that had used the FPU. Instructions in a failed IT condition are costed as if
executed (an M4 spends 1 cycle on them; only the upper bound should count more).
Data accesses go to SRAM (zero wait states) in both placements. Nothing here ran on a
real MCU: the bounds are a model over QEMU's instruction trace, not a measurement.
"""

from __future__ import annotations

import bisect
import re
import subprocess
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from fluxdrive.can.elf import function_ranges

__all__ = [
    "ENTRY_EXIT_LOWER",
    "ENTRY_EXIT_UPPER",
    "FLASH_WAIT_STATES",
    "CycleBounds",
    "Insn",
    "cost_trace",
    "disassemble",
    "function_ranges",
    "placement",
]

FLASH_WAIT_STATES = 4
"""STM32G474 flash wait states at 170 MHz (range 1 boost mode)."""
FLASH_LINE_BYTES = 8
"""Bytes per flash fetch (64-bit line)."""
ENTRY_EXIT_LOWER = 12 + 12
"""Exception entry + exit [cycles], no FP context to stack."""
ENTRY_EXIT_UPPER = 12 + 17 + 12 + 17
"""Entry + lazy FP stacking (17 words) + exit + FP unstacking [cycles]."""
CCM_RANGE = (0x1000_0000, 0x1000_8000)
"""The G474's 32 KB CCM SRAM on the instruction bus."""

_CONDS = "eq|ne|cs|hs|cc|lo|mi|pl|vs|vc|hi|ls|ge|lt|gt|le|al"
_OBJDUMP = re.compile(r"^\s*([0-9a-f]+):\s+((?:[0-9a-f]{4}\s?){1,2})\s+(\S+)\s*(.*)$")
_SYMBOL = re.compile(r"^\s*[0-9a-f]+ <([^>]+)>:$")


@dataclass(frozen=True)
class Insn:
    """One decoded instruction: address, size [bytes], base mnemonic (condition and width
    suffixes stripped), operands, and its class."""

    addr: int
    size: int
    op: str
    args: str
    cls: str
    regs: int = 0  # registers moved by a multiple load/store (D registers count 2)
    writes_pc: bool = False
    literal: bool = False  # a PC-relative load
    conditional: bool = False  # a condition code (or CBZ/CBNZ): may fall through


def _is_conditional(mnemonic: str) -> bool:
    m = mnemonic.split(".")[0].lower()
    if m in ("cbz", "cbnz"):
        return True
    cm = re.fullmatch(rf"(.+?)({_CONDS})", m)
    return bool(cm and cm.group(1) in _KNOWN and m not in _KNOWN)


def _base(mnemonic: str) -> str:
    m = mnemonic.split(".")[0].lower()
    if re.fullmatch(r"it[te]{0,3}", m):
        return "it"
    # strip a condition code: bne -> b, vmovle -> vmov, ldrbne -> ldrb, but not bl/bls...
    cm = re.fullmatch(rf"(.+?)({_CONDS})", m)
    if cm and cm.group(1) in _KNOWN:
        return cm.group(1)
    return m


_KNOWN = {
    "b", "bl", "blx", "bx", "cbz", "cbnz", "tbb", "tbh", "mov", "movs", "movw", "movt", "mvn",
    "add", "adds", "sub", "subs", "rsb", "cmp", "cmn", "tst", "and", "ands", "orr", "orrs",
    "eor", "bic", "bics", "lsl", "lsls", "lsr", "lsrs", "asr", "asrs", "ubfx", "sbfx", "bfi",
    "uxth", "uxtb", "sxth", "sxtb", "mul", "mla", "mls", "umull", "smull", "udiv", "sdiv",
    "ldr", "ldrb", "ldrh", "ldrsb", "ldrsh", "str", "strb", "strh", "ldrd", "strd", "vmov",
    "vadd", "vsub", "vmul", "vnmul", "vdiv", "vsqrt", "vcmp", "vcmpe", "vcvt", "vneg", "vabs",
    "vldr", "vstr", "vmrs", "vfma", "vfms", "vfnma", "vfnms", "vmla", "vmls", "vnmla", "vnmls",
    "addw", "subw", "clz", "neg", "negs", "mvns",
}  # fmt: skip

_MAC = {"vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms"}
_MULTI = {"ldm", "ldmia", "ldmdb", "stm", "stmia", "stmdb", "push", "pop"}
_VMULTI = {"vldm", "vldmia", "vldmdb", "vstm", "vstmia", "vstmdb", "vpush", "vpop"}
_BRANCH = {"b", "bl", "blx", "bx", "cbz", "cbnz", "tbb", "tbh"}
_SINGLE_MEM = re.compile(r"^(ldr|str)(b|h|sb|sh|ex|exb|exh|t|bt|ht)?$|^v(ldr|str)$")


def _reg_count(args: str) -> int:
    m = re.search(r"\{([^}]*)\}", args)
    if not m:
        return 0
    n = 0
    for part in m.group(1).split(","):
        part = part.strip()
        rng = re.fullmatch(r"([rsd])(\d+)-[rsd](\d+)", part)
        if rng:
            k = int(rng.group(3)) - int(rng.group(2)) + 1
            n += 2 * k if rng.group(1) == "d" else k
        elif part:
            n += 2 if part.startswith("d") else 1
    return n


def _classify(op: str, args: str) -> tuple[str, int, bool, bool]:
    """(class, registers, writes pc, literal load) of one instruction."""
    a = args.replace(" ", "")
    if op == "it":
        return "alu", 0, False, False
    if op in _BRANCH:
        return "branch", 0, True, False
    if op in ("vdiv", "vsqrt"):
        return "fdiv", 0, False, False
    if op in _MAC:
        return "fmac", 0, False, False
    if op in _VMULTI:
        return "multi", _reg_count(args), False, False
    if op in _MULTI:
        regs = _reg_count(args)
        return "multi", regs, "pc" in re.findall(r"\w+", a.split("{", 1)[-1]), False
    if op in ("ldrd", "strd"):
        return "dual", 2, False, False
    if _SINGLE_MEM.match(op):
        literal = "[pc" in a
        writes_pc = op.startswith("ldr") and a.startswith("pc,")
        return "mem", 0, writes_pc, literal
    if op == "vmov" and len(re.findall(r"\b[rs]\d+|\bd\d+|\b(?:ip|lr|sl|fp)\b", args)) >= 3:
        return "vmov2", 0, False, False
    if op.startswith("v"):
        return "fpu", 0, False, False
    if op in ("mla", "mls"):
        return "mac", 0, False, False
    if op in ("udiv", "sdiv"):
        return "div", 0, False, False
    writes_pc = a.startswith("pc,")
    return "alu", 0, writes_pc, False


def disassemble(elf: Path) -> dict[int, Insn]:
    """Every instruction of an image by address (arm-none-eabi-objdump -d)."""
    out = subprocess.run(
        ["arm-none-eabi-objdump", "-d", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    insns: dict[int, Insn] = {}
    for line in out.splitlines():
        m = _OBJDUMP.match(line)
        if m is None or m.group(3).startswith("."):
            continue
        addr = int(m.group(1), 16)
        size = len(m.group(2).replace(" ", "")) // 2
        op = _base(m.group(3))
        args = m.group(4).split(";")[0].strip()
        cls, regs, wpc, lit = _classify(op, args)
        cond = _is_conditional(m.group(3))
        insns[addr] = Insn(addr, size, op, args, cls, regs, wpc, lit, cond)
    return insns


def placement(g474_elf: Path) -> dict[str, str]:
    """Function name -> "ccm" or "flash" in the G474 image (a name defined in both: flash,
    the slower)."""
    where: dict[str, str] = {}
    for start, _end, name in function_ranges(g474_elf):
        region = "ccm" if CCM_RANGE[0] <= start < CCM_RANGE[1] else "flash"
        if where.get(name) != "flash":
            where[name] = region
    return where


@dataclass
class CycleBounds:
    """Lower and upper cycle bound of one interrupt, with what they are made of."""

    instructions: int = 0
    lower: int = 0
    upper: int = 0
    classes: Counter[str] = field(default_factory=Counter)
    by_function: Counter[str] = field(default_factory=Counter)  # upper-bound cycles


def _fn_lookup(ranges: list[tuple[int, int, str]]) -> Callable[[int], str]:
    starts = [r[0] for r in ranges]

    def fn(pc: int) -> str:
        i = bisect.bisect_right(starts, pc) - 1
        if i >= 0 and ranges[i][0] <= pc < ranges[i][1]:
            return ranges[i][2]
        return "?"

    return fn


class TraceCoster:
    """Costs instruction traces of one image (``elf``: the QEMU image the trace is of;
    ``where``: function placement of the target image, :func:`placement`)."""

    def __init__(self, elf: Path, where: dict[str, str]) -> None:
        self.insns = disassemble(elf)
        self._fn = _fn_lookup(function_ranges(elf))
        self.where = where
        self._fn_cache: dict[int, str] = {}

    def function(self, pc: int) -> str:
        f = self._fn_cache.get(pc)
        if f is None:
            f = self._fn(pc)
            self._fn_cache[pc] = f
        return f

    def cost(self, pcs: list[int], end_pc: int, entry_exit: bool = True) -> CycleBounds:
        """Bounds of one interrupt: ``pcs`` the executed instructions in order, ``end_pc``
        the instruction executed after the last one; ``entry_exit`` False: no exception
        entry and exit (a pass of the background loop)."""
        b = CycleBounds(instructions=len(pcs))
        prev_mem = False
        run_exec = 0  # upper-bound execution cycles of the current straight flash run
        run_bytes = 0
        nxt_list = [*pcs[1:], end_pc]
        for pc, nxt in zip(pcs, nxt_list, strict=True):
            ins = self.insns.get(pc)
            if ins is None:
                raise ValueError(f"no instruction at 0x{pc:08x} in the disassembly")
            fn = self.function(pc)
            flash = self.where.get(fn, "flash") == "flash"
            taken = nxt != pc + ins.size
            lo, hi = _cycles(ins, taken, prev_mem)
            prev_mem = ins.cls == "mem" and not ins.writes_pc
            if ins.literal:
                hi += FLASH_WAIT_STATES if flash else 1
            b.classes[ins.cls + ("_taken" if taken and ins.cls == "branch" else "")] += 1
            extra = 0
            if flash:
                run_exec += hi
                run_bytes += ins.size
                if taken:
                    lines = -(-run_bytes // FLASH_LINE_BYTES)
                    extra = max(0, (FLASH_WAIT_STATES + 1) * lines - run_exec)
                    extra += FLASH_WAIT_STATES  # the branch target's line
                    run_exec = run_bytes = 0
            elif run_exec or run_bytes:
                run_exec = run_bytes = 0
            b.lower += lo
            b.upper += hi + extra
            b.by_function[fn] += hi + extra
        if entry_exit:
            b.lower += ENTRY_EXIT_LOWER
            b.upper += ENTRY_EXIT_UPPER
        return b

    def cost_blocks(self, blocks: Mapping[tuple[int, int], int]) -> CycleBounds:
        """Bounds of one interrupt known only as executed basic blocks ((address, size) ->
        times executed, as an emulator's block hook counts them; the order is lost). A
        block's last branch counts as taken in the upper bound, and in the lower one only
        when it is unconditional; in flash every block starts a fresh line fetch (upper).
        These bracket :meth:`cost` of the same execution."""
        b = CycleBounds()
        for (start, size), times in blocks.items():
            pc, end = start, start + size
            lo_sum = hi_sum = 0
            prev_mem = False
            flash = self.where.get(self.function(start), "flash") == "flash"
            while pc < end:
                ins = self.insns.get(pc)
                if ins is None:
                    raise ValueError(f"no instruction at 0x{pc:08x} in the disassembly")
                last = pc + ins.size >= end
                branch = last and (ins.cls == "branch" or ins.writes_pc)
                lo, _ = _cycles(ins, branch and not ins.conditional, prev_mem)
                _, hi = _cycles(ins, branch, prev_mem)
                prev_mem = ins.cls == "mem" and not ins.writes_pc
                if ins.literal:
                    hi += FLASH_WAIT_STATES if flash else 1
                lo_sum += lo
                hi_sum += hi
                b.classes[ins.cls] += times
                b.instructions += times
                pc += ins.size
            if flash:
                lines = -(-size // FLASH_LINE_BYTES)
                hi_sum = max(hi_sum, (FLASH_WAIT_STATES + 1) * lines) + FLASH_WAIT_STATES
            b.lower += times * lo_sum
            b.upper += times * hi_sum
            b.by_function[self.function(start)] += times * hi_sum
        b.lower += ENTRY_EXIT_LOWER
        b.upper += ENTRY_EXIT_UPPER
        return b


def _cycles(ins: Insn, taken: bool, prev_mem: bool) -> tuple[int, int]:
    """(lower, upper) execution cycles of one instruction, memory wait states aside."""
    c = ins.cls
    if c == "alu":
        base = (1, 1)
    elif c == "mac":
        base = (2, 2)
    elif c == "div":
        base = (2, 12)
    elif c == "mem":
        base = (1 if prev_mem else 2, 2)
    elif c == "dual":
        base = (3, 3)
    elif c == "multi":
        base = (1 + ins.regs, 1 + ins.regs)
    elif c == "branch":
        base = (2, 2) if ins.op in ("tbb", "tbh") else (1, 1)  # a table branch loads first
    elif c == "fdiv":
        base = (14, 14)
    elif c == "fmac":
        base = (3, 3)
    elif c == "vmov2":
        base = (2, 2)
    else:  # fpu
        base = (1, 1)
    if taken and (c == "branch" or ins.writes_pc):
        return base[0] + 1, base[1] + 3
    return base


def cost_trace(elf: Path, g474_elf: Path, pcs: list[int], end_pc: int) -> CycleBounds:
    """One-shot :meth:`TraceCoster.cost` (tests)."""
    return TraceCoster(elf, placement(g474_elf)).cost(pcs, end_pc)
