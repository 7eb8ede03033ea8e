"""The C drive firmware on its target ISA: Cortex-M4F cross build, size, interrupt cost.

:func:`build_target` cross-compiles ``firmware/`` with Debian's ``arm-none-eabi-gcc``
(``-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard -O2``, warnings as errors)
into ``.ws/firmware/target``: ``fd_g474.elf`` (an STM32G474 memory map; flash and RAM from
``arm-none-eabi-size``) and ``fd_an386.elf`` (the same program for QEMU's ``mps2-an386``,
a Cortex-M4F board model).

:func:`count_isr_instructions` runs ``fd_an386.elf`` under ``qemu-system-arm`` with one
guest instruction per translation block (``-singlestep``) and block chaining off
(``-d exec,nochain``), so the execution log has one line per executed instruction. The
program (firmware/target/bench_main.c) calls ``fd_mark_begin(tag)`` before and
``fd_mark_end()`` after every period interrupt (``fd_core_period``); the instructions
executed between the two calls (the markers' own bodies excluded; the two call sites' few
instructions included) are one interrupt. Tag 1: host mode, tag 2: split mode.

This is an instruction count, not a cycle count: flash wait states (4 at 170 MHz on the
G474, partly hidden by its ART accelerator), FPU and load/store timing, branch refills and
interrupt entry/exit (about 12 cycles each way, more when the FP context is stacked) are
not in it. ``./fluxdrive benchmark firmware`` (:func:`bench_firmware`) prints the figures
(last line JSON) and writes ``results/firmware/target.json``, which
docs/firmware.md quotes.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from fluxdrive.can.firmware import FIRMWARE_DIR, FirmwareBuildError, _source_hash
from fluxdrive.core.paths import ROOT

__all__ = [
    "CPU_HZ",
    "PWM_HZ",
    "RESULTS_PATH",
    "build_target",
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


def build_target(force: bool = False) -> Path:
    """Cross-compile the target images (a no-op while no source changed)."""
    bdir = target_build_dir()
    bdir.mkdir(parents=True, exist_ok=True)
    stamp = bdir / ".fluxdrive-stamp"
    want = _source_hash("target " + sys.executable)
    elfs = [bdir / "fd_g474.elf", bdir / "fd_an386.elf"]
    if not force and all(e.is_file() for e in elfs) and stamp.is_file():
        if stamp.read_text() == want:
            return bdir
    log = bdir / "build.log"
    tdir = FIRMWARE_DIR / "target"
    steps = [
        ["cmake", "-S", str(tdir), "-B", str(bdir),
         f"-DCMAKE_TOOLCHAIN_FILE={tdir / 'arm-none-eabi.cmake'}",
         f"-DFD_PYTHON={sys.executable}", "-DCMAKE_BUILD_TYPE=Release"],
        ["cmake", "--build", str(bdir), "-j", "2"],
    ]  # fmt: skip
    with open(log, "w") as out:
        for cmd in steps:
            rc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, check=False)
            if rc.returncode != 0:
                raise FirmwareBuildError(
                    f"firmware target build failed: {' '.join(cmd[:2])} (log: {log})"
                )
    stamp.write_text(want)
    return bdir


def target_sizes(elf: Path) -> dict[str, int]:
    """text/data/bss of an image (arm-none-eabi-size, Berkeley format); flash = text +
    data (initial values), RAM = data + bss (bss includes the 4 KB main stack)."""
    out = subprocess.run(
        ["arm-none-eabi-size", str(elf)], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    text, data, bss = (int(x) for x in out[1].split()[:3])
    return {"text": text, "data": data, "bss": bss, "flash": text + data, "ram": data + bss}


def _symbol_ranges(elf: Path, names: tuple[str, ...]) -> dict[str, tuple[int, int]]:
    out = subprocess.run(
        ["arm-none-eabi-nm", "-S", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    ranges = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[3] in names:
            start = int(parts[0], 16) & ~1
            ranges[parts[3]] = (start, start + int(parts[1], 16))
    missing = set(names) - set(ranges)
    if missing:
        raise FirmwareBuildError(f"{elf}: symbols not found: {sorted(missing)}")
    return ranges


_TRACE = re.compile(r"^Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/")


def count_isr_instructions(elf: Path, timeout_s: float = 120.0) -> dict[int, list[int]]:
    """Executed instructions of every marked period interrupt, by tag (see module doc)."""
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
    counts: dict[int, list[int]] = {}
    tag_of_begin = _begin_tags(elf)
    inside = False
    n = 0
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
                    n = 0
                continue
            if e0 <= pc < e1:
                if inside and pc == e0:
                    tag = tag_of_begin[idx] if idx < len(tag_of_begin) else 0
                    counts.setdefault(tag, []).append(n)
                    idx += 1
                    inside = False
                continue
            if inside:
                n += 1
    trace.unlink(missing_ok=True)
    return counts


def _begin_tags(elf: Path) -> list[int]:
    """Tags of the marked interrupts in execution order: the bench program runs N_HOST
    host-mode periods (tag 1), then N_SPLIT split-mode periods (tag 2)."""
    src = (FIRMWARE_DIR / "target" / "bench_main.c").read_text()
    n_host = int(re.search(r"#define N_HOST (\d+)u", src).group(1))  # type: ignore[union-attr]
    n_split = int(re.search(r"#define N_SPLIT (\d+)u", src).group(1))  # type: ignore[union-attr]
    return [1] * n_host + [2] * n_split


def _summary(counts: list[int]) -> dict[str, Any]:
    budget = CPU_HZ / PWM_HZ
    worst = max(counts)
    return {
        "periods": len(counts),
        "instructions_max": worst,
        "instructions_median": sorted(counts)[len(counts) // 2],
        "instructions_min": min(counts),
        "percent_of_period_at_1_cycle_per_instruction": round(100.0 * worst / budget, 2),
    }


def run_benchmark() -> dict[str, Any]:
    """Build, size, count; returns the results record (also written to RESULTS_PATH)."""
    bdir = build_target()
    counts = count_isr_instructions(bdir / "fd_an386.elf")
    gcc = subprocess.run(
        ["arm-none-eabi-gcc", "--version"], capture_output=True, text=True, check=True
    ).stdout.splitlines()[0]
    qemu = subprocess.run(
        ["qemu-system-arm", "--version"], capture_output=True, text=True, check=True
    ).stdout.splitlines()[0]
    rec = {
        "part": "STM32G474 (Cortex-M4F, 170 MHz, 512 KB flash, 96 KB SRAM1+2 used)",
        "compiler": gcc,
        "flags": "-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard -O2 -Werror",
        "size_g474": target_sizes(bdir / "fd_g474.elf"),
        "emulator": qemu + ", machine mps2-an386, -singlestep -d exec,nochain",
        "budget_instructions_per_period": int(CPU_HZ / PWM_HZ),
        "host_mode": _summary(counts[1]),
        "split_mode": _summary(counts[2]),
        "method": "instructions executed between fd_mark_begin/fd_mark_end around "
        "fd_core_period (firmware/target/bench_main.c), counted from QEMU's per-instruction "
        "execution log; instruction count, not cycle count",
        "never_run_on_hardware": True,
    }
    RESULTS_PATH.parent.mkdir(parents=True, exist_ok=True)
    RESULTS_PATH.write_text(json.dumps(rec, indent=2) + "\n")
    return rec


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
    budget = rec["budget_instructions_per_period"]
    for mode in ("host_mode", "split_mode"):
        m = rec[mode]
        print(
            f"{mode:<10} period interrupt: max {m['instructions_max']} instructions, median "
            f"{m['instructions_median']} over {m['periods']} periods = "
            f"{m['percent_of_period_at_1_cycle_per_instruction']} % of {budget} cycles "
            "(at 1 cycle per instruction; instruction count, not cycle count)"
        )
    print(f"written {RESULTS_PATH.relative_to(ROOT)}")
    return rec
