"""The C drive firmware on its target ISA: Cortex-M4F cross build, size, interrupt cost.

:func:`build_target` cross-compiles ``firmware/`` with Debian's ``arm-none-eabi-gcc``
(``-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard -O2``, warnings as errors)
into ``.ws/firmware/target``: ``fd_g474.elf`` (an STM32G474 memory map; flash and RAM from
``arm-none-eabi-size``) and ``fd_an386.elf`` (the same program for QEMU's ``mps2-an386``,
a Cortex-M4F board model).

:func:`trace_isrs` runs ``fd_an386.elf`` under ``qemu-system-arm`` with one guest
instruction per translation block (``-singlestep``) and block chaining off (``-d
exec,nochain``), so the execution log has one line per executed instruction. The program
(firmware/target/bench_main.c) calls ``fd_mark_begin(tag)`` before and ``fd_mark_end()``
after every period interrupt (``fd_core_period``); the instructions executed between the two
calls (the markers' own bodies excluded; the two call sites' few instructions included) are
one interrupt. Tag 1: host mode, tag 2: split mode.

An instruction count is not a cycle count: :mod:`fluxdrive.can.firmware_cycles` costs each
executed instruction with Cortex-M4F timings (FPU divides, loads and stores, taken
branches, interrupt entry/exit, flash wait states where the G474 image places the code)
into a lower and an upper cycle bound. ``./fluxdrive benchmark firmware``
(:func:`bench_firmware`) prints the figures (last line JSON) and writes
``results/firmware/target.json``, which README.md and docs/firmware.md quote.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fluxdrive.can.elf import elf_symbols
from fluxdrive.can.firmware import FIRMWARE_DIR, FirmwareBuildError, _source_hash
from fluxdrive.can.firmware_cycles import (
    ENTRY_EXIT_LOWER,
    ENTRY_EXIT_UPPER,
    FLASH_WAIT_STATES,
    CycleBounds,
    TraceCoster,
    placement,
)
from fluxdrive.core.paths import ROOT

__all__ = [
    "CPU_HZ",
    "PWM_HZ",
    "RESULTS_PATH",
    "build_target",
    "cross_build",
    "bench_firmware",
    "count_isr_instructions",
    "target_available",
    "target_sizes",
]

CPU_HZ = 170e6
"""STM32G474 core clock [Hz]."""
PWM_HZ = 10e3
"""PWM (period interrupt) rate [Hz]."""
RESULTS_PATH = ROOT / "results" / "firmware" / "target.json"
_TOOLS = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm", "qemu-system-arm")


def target_available() -> str | None:
    """None if the cross toolchain and QEMU are on PATH, else what is missing."""
    missing = [t for t in _TOOLS if shutil.which(t) is None]
    return ", ".join(missing) if missing else None


def target_build_dir() -> Path:
    return ROOT / ".ws" / "firmware" / "target"


def cross_build(src: Path, bdir: Path, elfs: Sequence[str], what: str, force: bool = False) -> Path:
    """Cross-compile the CMake project ``src`` (Debian's arm-none-eabi-gcc, the toolchain
    file firmware/target/arm-none-eabi.cmake, warnings as errors) into ``bdir``; a no-op
    while the images ``elfs`` exist and no firmware source changed (a content hash, like
    the host build's). ``what`` names the build in its error. The one cross build of the
    target images (here) and the board images (:func:`fluxdrive.can.vboard.build_board`)."""
    bdir.mkdir(parents=True, exist_ok=True)
    stamp = bdir / ".fluxdrive-stamp"
    want = _source_hash(f"{what} {sys.executable}")
    if not force and all((bdir / e).is_file() for e in elfs) and stamp.is_file():
        if stamp.read_text() == want:
            return bdir
    log = bdir / "build.log"
    steps = [
        ["cmake", "-S", str(src), "-B", str(bdir),
         f"-DCMAKE_TOOLCHAIN_FILE={FIRMWARE_DIR / 'target' / 'arm-none-eabi.cmake'}",
         f"-DFD_PYTHON={sys.executable}", "-DCMAKE_BUILD_TYPE=Release"],
        ["cmake", "--build", str(bdir), "-j", "2"],
    ]  # fmt: skip
    with open(log, "w") as out:
        for cmd in steps:
            rc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, check=False)
            if rc.returncode != 0:
                raise FirmwareBuildError(f"{what} build failed: {' '.join(cmd[:2])} (log: {log})")
    stamp.write_text(want)
    return bdir


def build_target(force: bool = False) -> Path:
    """Cross-compile the target images (a no-op while no source changed)."""
    return cross_build(
        FIRMWARE_DIR / "target",
        target_build_dir(),
        ("fd_g474.elf", "fd_an386.elf"),
        "firmware target",
        force,
    )


def target_sizes(elf: Path) -> dict[str, int]:
    """text/data/bss of an image (arm-none-eabi-size, Berkeley format); flash = text +
    data (initial values), RAM = data + bss (bss includes the 4 KB main stack)."""
    out = subprocess.run(
        ["arm-none-eabi-size", str(elf)], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    text, data, bss = (int(x) for x in out[1].split()[:3])
    return {"text": text, "data": data, "bss": bss, "flash": text + data, "ram": data + bss}


def _symbol_ranges(elf: Path, names: tuple[str, ...]) -> dict[str, tuple[int, int]]:
    syms = elf_symbols(elf)
    missing = set(names) - set(syms)
    if missing:
        raise FirmwareBuildError(f"{elf}: symbols not found: {sorted(missing)}")
    return {n: (syms[n].value & ~1, (syms[n].value & ~1) + syms[n].size) for n in names}


_TRACE = re.compile(r"^Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/")


def trace_isrs(elf: Path, timeout_s: float = 120.0) -> dict[int, list[tuple[list[int], int]]]:
    """The executed program counters of every marked period interrupt, by tag (see module
    doc): per interrupt the instructions in order and the one executed after the last."""
    rng = _symbol_ranges(elf, ("fd_mark_begin", "fd_mark_end"))
    trace = elf.parent / "exec-trace.log"
    cmd = [
        "qemu-system-arm", "-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic",
        "-monitor", "none", "-serial", "none",
        "-semihosting-config", "enable=on,target=native",
        "-kernel", str(elf), "-singlestep", "-d", "exec,nochain", "-D", str(trace),
    ]  # fmt: skip
    subprocess.run(cmd, check=True, timeout=timeout_s, capture_output=True)
    b0, b1 = rng["fd_mark_begin"]
    e0, e1 = rng["fd_mark_end"]
    isrs: dict[int, list[tuple[list[int], int]]] = {}
    tag_of_begin = _begin_tags(elf)
    inside = False
    pcs: list[int] = []
    idx = 0
    with open(trace) as f:
        for line in f:
            m = _TRACE.match(line)
            if m is None:
                continue
            pc = int(m.group(1), 16)
            if b0 <= pc < b1:
                if not inside and pc == b0:
                    inside = True
                    pcs = []
                continue
            if e0 <= pc < e1:
                if inside and pc == e0:
                    tag = tag_of_begin[idx] if idx < len(tag_of_begin) else 0
                    isrs.setdefault(tag, []).append((pcs, pc))
                    idx += 1
                    inside = False
                continue
            if inside:
                pcs.append(pc)
    trace.unlink(missing_ok=True)
    return isrs


def count_isr_instructions(elf: Path, timeout_s: float = 120.0) -> dict[int, list[int]]:
    """Executed instructions of every marked period interrupt, by tag (see module doc)."""
    return {tag: [len(pcs) for pcs, _ in runs] for tag, runs in trace_isrs(elf, timeout_s).items()}


def _begin_tags(elf: Path) -> list[int]:
    """Tags of the marked interrupts in execution order: the bench program runs N_HOST
    host-mode periods (tag 1), then N_SPLIT split-mode periods (tag 2)."""
    src = (FIRMWARE_DIR / "target" / "bench_main.c").read_text()
    n_host = int(re.search(r"#define N_HOST (\d+)u", src).group(1))  # type: ignore[union-attr]
    n_split = int(re.search(r"#define N_SPLIT (\d+)u", src).group(1))  # type: ignore[union-attr]
    return [1] * n_host + [2] * n_split


def _summary(bounds: list[CycleBounds]) -> dict[str, Any]:
    budget = CPU_HZ / PWM_HZ
    counts = [b.instructions for b in bounds]
    lower = sorted(b.lower for b in bounds)
    upper = sorted(b.upper for b in bounds)
    worst = max(bounds, key=lambda b: b.upper)
    return {
        "periods": len(counts),
        "instructions_max": max(counts),
        "instructions_median": sorted(counts)[len(counts) // 2],
        "instructions_min": min(counts),
        "percent_of_period_at_1_cycle_per_instruction": round(100.0 * max(counts) / budget, 2),
        "cycles_lower_max": lower[-1],
        "cycles_lower_median": lower[len(lower) // 2],
        "cycles_upper_max": upper[-1],
        "cycles_upper_median": upper[len(upper) // 2],
        "percent_of_period_lower": round(100.0 * lower[-1] / budget, 2),
        "percent_of_period_upper": round(100.0 * upper[-1] / budget, 2),
        "worst_upper_instruction_classes": dict(worst.classes.most_common()),
        "worst_upper_cycles_by_function": dict(worst.by_function.most_common(12)),
    }


def run_benchmark() -> dict[str, Any]:
    """Build, size, trace, cost; returns the results record (also written to RESULTS_PATH)."""
    bdir = build_target()
    elf = bdir / "fd_an386.elf"
    isrs = trace_isrs(elf)
    where = placement(bdir / "fd_g474.elf")
    coster = TraceCoster(elf, where)
    bounds = {tag: [coster.cost(pcs, end) for pcs, end in runs] for tag, runs in isrs.items()}
    executed = {coster.function(pc) for runs in isrs.values() for pcs, _ in runs for pc in pcs}
    gcc = subprocess.run(
        ["arm-none-eabi-gcc", "--version"], capture_output=True, text=True, check=True
    ).stdout.splitlines()[0]
    qemu = subprocess.run(
        ["qemu-system-arm", "--version"], capture_output=True, text=True, check=True
    ).stdout.splitlines()[0]
    host, split = _summary(bounds[1]), _summary(bounds[2])
    rec = {
        "part": "STM32G474 (Cortex-M4F, 170 MHz, 512 KB flash, 96 KB SRAM1+2, 32 KB CCM SRAM)",
        "compiler": gcc,
        "flags": "-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard -O2 -Werror",
        "size_g474": target_sizes(bdir / "fd_g474.elf"),
        "ccm_code_bytes": ccm_bytes(bdir / "fd_g474.elf"),
        "emulator": qemu + ", machine mps2-an386, -singlestep -d exec,nochain",
        "budget_instructions_per_period": int(CPU_HZ / PWM_HZ),
        "budget_cycles_per_period": int(CPU_HZ / PWM_HZ),
        "host_mode": host,
        "split_mode": split,
        "worst_percent_of_period_upper": max(
            host["percent_of_period_upper"], split["percent_of_period_upper"]
        ),
        "executed_functions": {
            "ccm": sorted(f for f in executed if where.get(f) == "ccm"),
            "flash": sorted(f for f in executed if where.get(f, "flash") == "flash"),
        },
        "cycle_model": {
            "flash_wait_states": FLASH_WAIT_STATES,
            "entry_exit_lower": ENTRY_EXIT_LOWER,
            "entry_exit_upper": ENTRY_EXIT_UPPER,
            "doc": "fluxdrive.can.firmware_cycles (docs/firmware.md, Target numbers)",
        },
        "method": "instructions executed between fd_mark_begin/fd_mark_end around "
        "fd_core_period (firmware/target/bench_main.c), from QEMU's per-instruction "
        "execution log; each costed with Cortex-M4F timings into a lower and an upper cycle "
        "bound (fluxdrive.can.firmware_cycles), code placement from the G474 image",
        "never_run_on_hardware": True,
    }
    RESULTS_PATH.parent.mkdir(parents=True, exist_ok=True)
    RESULTS_PATH.write_text(json.dumps(rec, indent=2) + "\n")
    return rec


def ccm_bytes(elf: Path) -> int:
    """Bytes of the image's .ccm section (the interrupt's code in CCM SRAM)."""
    out = subprocess.run(
        ["arm-none-eabi-size", "-A", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    for line in out.splitlines():
        parts = line.split()
        if parts and parts[0] == ".ccm":
            return int(parts[1])
    return 0


def bench_firmware(argv: list[str]) -> dict[str, Any]:
    """`./fluxdrive benchmark firmware`: cross build, flash/RAM, the period interrupt's
    instruction count in host and split mode against 170 MHz / 10 kHz; writes
    results/firmware/target.json (the caller prints the record as the last line)."""
    from fluxdrive.core.schema import Parser

    ap = Parser(prog="fluxdrive benchmark firmware", description=__doc__)
    ap.parse_args(argv)
    missing = target_available()
    if missing:
        print(
            f"benchmark firmware: missing {missing}; tools/bootstrap.sh installs them "
            "(Debian: gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    try:
        rec = run_benchmark()
    except (FirmwareBuildError, subprocess.SubprocessError) as exc:
        print(f"benchmark firmware: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    s = rec["size_g474"]
    print(f"target  {rec['part']}; {rec['compiler']}")
    print(
        f"size    flash {s['flash']} B (text {s['text']} + data {s['data']}), "
        f"RAM {s['ram']} B (data {s['data']} + bss {s['bss']}, incl. 4096 B stack)"
    )
    budget = rec["budget_cycles_per_period"]
    print(f"ccm     {rec['ccm_code_bytes']} B of the interrupt's code and constants in CCM SRAM")
    for mode in ("host_mode", "split_mode"):
        m = rec[mode]
        print(
            f"{mode:<10} period interrupt over {m['periods']} periods: max "
            f"{m['instructions_max']} instructions (median {m['instructions_median']}); "
            f"cycles {m['cycles_lower_max']}..{m['cycles_upper_max']} (lower..upper bound, "
            f"worst) = {m['percent_of_period_lower']}..{m['percent_of_period_upper']} % of "
            f"{budget} cycles"
        )
    print(
        f"worst   {rec['worst_percent_of_period_upper']} % of a 10 kHz period at 170 MHz by "
        "the upper bound (goal <= 30 %); a model over QEMU's trace, never run on hardware"
    )
    print(f"written {RESULTS_PATH.relative_to(ROOT)}")
    return rec
