"""The cycle model of ``benchmark firmware`` (fluxdrive.can.firmware_cycles): instruction
classes from objdump's text, the bounds of small hand-made traces worked out from the
model's table, and the whole image: the interrupt's code in CCM SRAM and, over QEMU's trace,
lower <= upper with every bound above one cycle per instruction."""

from __future__ import annotations

from collections import Counter

import pytest
from fluxdrive.can import firmware_cycles as fc

# (objdump mnemonic, operands) -> (class, registers, writes pc, literal load)
CASES = {
    ("vdiv.f32", "s15, s14, s13"): ("fdiv", 0, False, False),
    ("vfma.f32", "s0, s1, s2"): ("fmac", 0, False, False),
    ("vmul.f32", "s0, s1, s2"): ("fpu", 0, False, False),
    ("vmov", "r0, r1, d8"): ("vmov2", 0, False, False),
    ("vmov", "s0, r3"): ("fpu", 0, False, False),
    ("ldr", "r3, [pc, #24]"): ("mem", 0, False, True),
    ("ldrb.w", "r2, [r4, #37]"): ("mem", 0, False, False),
    ("vldr", "s15, [r4, #8]"): ("mem", 0, False, False),
    ("strd", "r2, r3, [sp, #8]"): ("dual", 2, False, False),
    ("push", "{r4, r5, r6, lr}"): ("multi", 4, False, False),
    ("pop", "{r4, r5, r6, pc}"): ("multi", 4, True, False),
    ("vpush", "{d8-d11}"): ("multi", 8, False, False),
    ("bne.n", "1a2 <f+0x1a>"): ("branch", 0, True, False),
    ("bl", "290c <cosf>"): ("branch", 0, True, False),
    ("movne", "r0, #1"): ("alu", 0, False, False),
    ("itett", "ge"): ("alu", 0, False, False),
    ("mla", "r0, r1, r2, r3"): ("mac", 0, False, False),
    ("udiv", "r0, r1, r2"): ("div", 0, False, False),
}


@pytest.mark.parametrize(("mnemonic", "args"), list(CASES))
def test_instruction_classes(mnemonic, args):
    assert fc._classify(fc._base(mnemonic), args) == CASES[(mnemonic, args)]


def _coster(program: list[tuple[int, int, str, str]], region: str) -> fc.TraceCoster:
    c = fc.TraceCoster.__new__(fc.TraceCoster)
    c.insns = {}
    for addr, size, mnem, args in program:
        op = fc._base(mnem)
        cls, regs, wpc, lit = fc._classify(op, args)
        c.insns[addr] = fc.Insn(addr, size, op, args, cls, regs, wpc, lit)
    c._fn = lambda pc: "f"
    c.where = {"f": region}
    c._fn_cache = {}
    return c


LOOP = [
    (0x0, 4, "vdiv.f32", "s0, s1, s2"),
    (0x4, 2, "ldr", "r0, [r1, #0]"),
    (0x6, 2, "ldr", "r2, [r1, #4]"),
    (0x8, 2, "bne.n", "0 <f>"),
]


def test_bounds_of_a_small_trace_in_ccm_and_in_flash():
    pcs, end = [0x0, 0x4, 0x6, 0x8], 0x0  # the branch is taken
    ccm = _coster(LOOP, "ccm").cost(pcs, end)
    # lower: VDIV 14 + LDR 2 + LDR 1 (pipelined behind the first) + taken branch 1+1
    assert ccm.lower == 14 + 2 + 1 + 2 + fc.ENTRY_EXIT_LOWER
    # upper: VDIV 14 + LDR 2 + LDR 2 + taken branch 1+3
    assert ccm.upper == 14 + 2 + 2 + 4 + fc.ENTRY_EXIT_UPPER
    flash = _coster(LOOP, "flash").cost(pcs, end)
    # 10 bytes = 2 flash lines = 10 cycles of fetch < 22 of execution: only the branch
    # target's line costs its 4 wait states
    assert flash.lower == ccm.lower
    assert flash.upper == ccm.upper + fc.FLASH_WAIT_STATES
    assert flash.classes["branch_taken"] == 1 and flash.classes["fdiv"] == 1


def test_table_branch_loads_before_it_branches():
    prog = [(0x0, 4, "tbb", "[pc, r3]"), (0x10, 2, "movs", "r0, #1")]
    b = _coster(prog, "ccm").cost([0x0, 0x10], 0x12)
    assert b.lower == 3 + 1 + fc.ENTRY_EXIT_LOWER and b.upper == 5 + 1 + fc.ENTRY_EXIT_UPPER


def test_flash_fetch_bounds_a_straight_run():
    """Eight single-cycle 32-bit instructions and a taken 32-bit branch: 36 bytes are five
    64-bit lines, 5 cycles each with 4 wait states, more than the 12 cycles they execute."""
    prog = [(4 * i, 4, "add.w", "r0, r0, #1") for i in range(8)] + [(32, 4, "b.w", "0 <f>")]
    pcs = [4 * i for i in range(9)]
    b = _coster(prog, "flash").cost(pcs, 0)
    assert b.upper == 5 * 5 + fc.FLASH_WAIT_STATES + fc.ENTRY_EXIT_UPPER
    assert _coster(prog, "ccm").cost(pcs, 0).upper == 8 + 4 + fc.ENTRY_EXIT_UPPER


def test_image_places_the_interrupt_in_ccm_and_bounds_its_trace():
    from fluxdrive.can import firmware_target as ft

    missing = ft.target_available()
    if missing:
        pytest.fail(f"no ARM toolchain or QEMU ({missing}); tools/bootstrap.sh installs them")
    bdir = ft.build_target()
    where = fc.placement(bdir / "fd_g474.elf")
    for fn in ("fd_core_period", "fd_current_loop", "fd_can_sample_fd_pack", "fd_hal_can_tx"):
        assert where[fn] == "ccm", fn
    # the reset handler fills .ccm through newlib's memcpy: it must not sit there itself;
    # memset (what the generated codec clears buffers with) runs only after, from CCM
    assert where["Reset_Handler"] == where["memcpy"] == "flash"
    assert where["memset"] == "ccm"
    isrs = ft.trace_isrs(bdir / "fd_an386.elf")
    coster = fc.TraceCoster(bdir / "fd_an386.elf", where)
    for tag in (1, 2):
        pcs, end = isrs[tag][-1]
        b = coster.cost(pcs, end)
        assert len(pcs) < b.lower < b.upper, (tag, b.lower, b.upper)
        assert sum(b.classes.values()) == len(pcs)
        assert "sinf" not in b.by_function and "memcpy" not in b.by_function
        # the same execution known only as counted basic blocks (what the virtual board's
        # block hook records): bounds that bracket the ordered trace's
        blocks: Counter[tuple[int, int]] = Counter()
        start = pcs[0]
        for pc, nxt in zip(pcs, [*pcs[1:], end], strict=True):
            if nxt != pc + coster.insns[pc].size:
                blocks[(start, pc + coster.insns[pc].size - start)] += 1
                start = nxt
        bb = coster.cost_blocks(blocks)
        assert bb.instructions == len(pcs)
        assert bb.lower <= b.lower and bb.upper >= b.upper, (
            tag,
            bb.lower,
            b.lower,
            bb.upper,
            b.upper,
        )
        assert bb.upper < 1.2 * b.upper
