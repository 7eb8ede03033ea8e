"""Register definitions of the STM32G474 board port, generated from the stm32g4 crate.

The data: the ``stm32g4`` crate (svd2rust output of the stm32-rs project's patched
STM32G474 SVD), pinned to one version in ``tools/g474-registers/Cargo.toml`` and brought
by cargo (``cargo fetch``); nothing is downloaded at run time. :func:`generate` reads, for
the peripherals and registers the port uses (:data:`USED`): base addresses, register
offsets, reset values, bit fields, and the interrupt numbers, and writes

* ``firmware/board/nucleo_g474/g474_regs.h`` (the C header the board HAL includes), and
* ``python/fluxdrive/can/g474_regmap.py`` (the same map for the virtual board).

Both outputs are committed; ``tests/test_board_g474.py`` regenerates them from the pinned
crate and fails when they differ. ``python -m fluxdrive.can.g474gen`` rewrites them.
Core peripherals of the Cortex-M4 (NVIC, SCB, SysTick) are the architecture's, not the
device's, and are written in the board code from the ARMv7-M manual.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from fluxdrive.core.paths import ROOT

__all__ = ["CRATE_MANIFEST", "HEADER", "PYMAP", "USED", "crate_dir", "generate", "render"]

BOARD_DIR = ROOT / "firmware" / "board" / "nucleo_g474"
CRATE_MANIFEST = ROOT / "tools" / "g474-registers" / "Cargo.toml"
HEADER = BOARD_DIR / "g474_regs.h"
PYMAP = ROOT / "python" / "fluxdrive" / "can" / "g474_regmap.py"

_TIM_PWM = ("cr1", "cr2", "smcr", "dier", "sr", "egr", "ccmr1_output", "ccmr2_output", "ccer",
            "cnt", "psc", "arr", "rcr", "ccr1", "ccr2", "ccr3", "ccr4", "bdtr", "af1")  # fmt: skip
_TIM_CAP = ("cr1", "cr2", "smcr", "dier", "sr", "egr", "ccmr1_input", "ccmr2_input", "ccer",
            "cnt", "psc", "arr", "ccr1", "ccr2", "ccr3", "ccr4")  # fmt: skip
_GPIO = ("moder", "otyper", "ospeedr", "pupdr", "idr", "odr", "bsrr", "afrl", "afrh")
_ADC = ("isr", "ier", "cr", "cfgr", "cfgr2", "smpr1", "smpr2", "jsqr", "jdr1", "jdr2", "jdr3",
        "jdr4", "difsel")  # fmt: skip

USED: dict[str, tuple[str, ...]] = {
    "RCC": ("cr", "cfgr", "pllcfgr", "ahb1enr", "ahb2enr", "apb1enr1", "apb2enr", "ccipr", "csr"),
    "FLASH": ("acr", "keyr", "sr", "cr", "optr"),
    "PWR": ("cr5",),
    "GPIOA": _GPIO,
    "GPIOB": _GPIO,
    "GPIOC": _GPIO,
    "TIM1": _TIM_PWM,
    "TIM2": ("cr1", "egr", "cnt", "psc", "arr"),
    "TIM3": _TIM_CAP,
    "TIM4": ("cr1", "smcr", "ccmr1_input", "ccer", "cnt", "arr"),
    "TIM5": _TIM_CAP,
    "TIM8": _TIM_CAP,
    "ADC1": _ADC,
    "ADC2": _ADC,
    "ADC12_COMMON": ("ccr",),
    "COMP": ("c1csr", "c2csr", "c4csr"),
    "DAC3": ("cr", "dhr12r1", "dhr12r2"),
    "FDCAN1": ("cccr", "nbtp", "dbtp", "tdcr", "ecr", "psr", "ir", "ie", "ils", "ile", "rxgfc",
               "rxf0s", "rxf0a", "rxf1s", "rxf1a", "txbc", "txfqs", "txbar", "txbrp", "ckdiv"),
    "IWDG": ("kr", "pr", "rlr", "sr"),
}  # fmt: skip
"""Peripheral (the crate's name) -> the registers the port uses (svd2rust accessor names)."""

SRAMCAN_BASE = 0x4000A400
"""FDCAN message RAM (RM0440 memory map); not a register block in the SVD."""


def crate_dir() -> Path:
    """The pinned stm32g4 crate's source folder (``cargo fetch`` first)."""
    subprocess.run(
        ["cargo", "fetch", "--manifest-path", str(CRATE_MANIFEST)],
        check=True,
        capture_output=True,
    )
    meta = subprocess.run(
        ["cargo", "metadata", "--offline", "--format-version", "1",
         "--manifest-path", str(CRATE_MANIFEST)],
        check=True, capture_output=True, text=True,
    ).stdout  # fmt: skip
    for pkg in json.loads(meta)["packages"]:
        if pkg["name"] == "stm32g4":
            return Path(pkg["manifest_path"]).parent
    raise FileNotFoundError("stm32g4 not in the registers manifest's dependencies")


_PERIPH = re.compile(r"pub type (\w+) = crate::Periph<(\w+)::RegisterBlock, (0x[0-9a-f_]+)>;")
_IRQ = re.compile(r"^\s+(\w+) = (\d+),$", re.M)
_ACCESSOR = re.compile(
    r"///(0x[0-9a-f]+) - [^\n]*\n(?:\s*#\[[^\n]*\n)*\s*pub const fn (\w+)\(&self\) -> &(\w+)"
)
_REGTYPE = re.compile(r"pub type (\w+) = crate::Reg<(\w+)::\w+>;")
_REUSE = re.compile(r"pub use crate::stm32g474::(\w+)::(\w+);")
_RESET = re.compile(r"const RESET_VALUE: u32 = (0x[0-9a-f_]+|\d+);")
_FIELD = re.compile(
    r"///Bits? (\d+)(?::(\d+))? - [^\n]*\n(?:\s*#\[[^\n]*\n)*\s*pub fn (\w+)\(&(?:mut )?self\)"
)


def _int(s: str) -> int:
    return int(s.replace("_", ""), 0)


def _device(src: Path) -> tuple[dict[str, tuple[str, int]], dict[str, int]]:
    mod = (src / "mod.rs").read_text()
    periph = {m[0]: (m[1], _int(m[2])) for m in _PERIPH.findall(mod)}
    body = mod[mod.index("pub enum Interrupt {") :]
    body = body[: body.index("}")]
    irqs = {name: int(n) for name, n in _IRQ.findall(body)}
    return periph, irqs


def _registers(src: Path, module: str, names: tuple[str, ...]) -> list[dict]:
    text = (src / f"{module}.rs").read_text()
    acc = {name: (_int(off), typ) for off, name, typ in _ACCESSOR.findall(text)}
    files = {typ: (module, f) for typ, f in _REGTYPE.findall(text)}
    for other, typ in _REUSE.findall(text):  # a register type shared with another block
        if typ.isupper() and typ not in files:
            ftext = (src / f"{other}.rs").read_text()
            files.update({t: (other, f) for t, f in _REGTYPE.findall(ftext) if t == typ})
    out = []
    for name in names:
        if name not in acc:
            raise KeyError(f"{module}: no register {name}")
        off, typ = acc[name]
        rmod, rfile = files[typ]
        rtext = (src / rmod / f"{rfile}.rs").read_text()
        m = _RESET.search(rtext)
        fields: dict[str, tuple[int, int]] = {}
        for lo, hi, fname in _FIELD.findall(rtext):
            a = int(lo)
            width = int(hi) - a + 1 if hi else 1
            fields.setdefault(fname, (a, width))
        out.append({"name": name, "offset": off, "reset": _int(m[1]) if m else 0, "fields": fields})
    return out


def generate(src_crate: Path) -> dict:
    """The register map of :data:`USED` from the crate at ``src_crate``."""
    src = src_crate / "src" / "stm32g474"
    periph, irqs = _device(src)
    out: dict = {"peripherals": {}, "irqs": irqs}
    for p, regs in USED.items():
        module, base = periph[p]
        out["peripherals"][p] = {"base": base, "registers": _registers(src, module, regs)}
    return out


def _cname(s: str) -> str:
    return s.upper()


def render(data: dict, version: str) -> tuple[str, str]:
    """(C header, Python module) text of a register map."""
    h = [
        "/* STM32G474 registers of the fluxdrive board port. GENERATED by",
        f" * python/fluxdrive/can/g474gen.py from the stm32g4 crate {version} (svd2rust output of",
        " * the stm32-rs patched SVD); do not edit. Only the registers the port uses. */",
        "#ifndef G474_REGS_H",
        "#define G474_REGS_H",
        "",
        "#include <stdint.h>",
        "",
        "#define G4_REG(addr) (*(volatile uint32_t *)(uintptr_t)(addr))",
        f"#define G4_SRAMCAN_BASE 0x{SRAMCAN_BASE:08X}u",
    ]
    for p, d in data["peripherals"].items():
        h.append("")
        h.append(f"#define G4_{p}_BASE 0x{d['base']:08X}u")
        for r in d["registers"]:
            rn = f"G4_{p}_{_cname(r['name'])}"
            h.append(f"#define {rn} G4_REG(G4_{p}_BASE + 0x{r['offset']:03X}u)")
            h.append(f"#define {rn}_RESET 0x{r['reset']:08X}u")
            for f, (pos, width) in r["fields"].items():
                mask = ((1 << width) - 1) << pos
                h.append(f"#define {rn}_{_cname(f)}_Pos {pos}u")
                h.append(f"#define {rn}_{_cname(f)}_Msk 0x{mask:08X}u")
    h.append("")
    irqs = data["irqs"]
    for name, n in irqs.items():
        h.append(f"#define G4_IRQ_{name} {n}")
    count = max(irqs.values()) + 1
    h.append(f"#define G4_IRQ_COUNT {count}")
    by_n = {n: name for name, n in irqs.items()}
    h.append("/* X(n, name) for every device interrupt line; reserved lines: X(n, RESERVED) */")
    h.append("#define G4_IRQ_LIST(X) \\")
    for n in range(count):
        sep = " \\" if n < count - 1 else ""
        h.append(f"    X({n}, {by_n.get(n, 'RESERVED')}){sep}")
    h += ["", "#endif /* G474_REGS_H */", ""]

    py = [
        '"""STM32G474 register map of the board port. GENERATED by fluxdrive.can.g474gen from',
        f"the stm32g4 crate {version} (svd2rust output of the stm32-rs patched SVD); do not edit.",
        '"""',
        "",
        "# fmt: off",
        f"SRAMCAN_BASE = 0x{SRAMCAN_BASE:08X}",
        "BASE: dict[str, int] = {",
    ]
    for p, d in data["peripherals"].items():
        py.append(f'    "{p}": 0x{d["base"]:08X},')
    py.append("}")
    py.append('"""Peripheral base addresses."""')
    py.append("REG: dict[str, tuple[int, int]] = {")
    for p, d in data["peripherals"].items():
        for r in d["registers"]:
            py.append(
                f'    "{p}_{_cname(r["name"])}": (0x{d["base"] + r["offset"]:08X}, '
                f"0x{r['reset']:08X}),"
            )
    py.append("}")
    py.append('"""PERIPH_REG -> (address, reset value)."""')
    py.append("FIELD: dict[str, tuple[int, int]] = {")
    for p, d in data["peripherals"].items():
        for r in d["registers"]:
            for f, (pos, width) in r["fields"].items():
                py.append(f'    "{p}_{_cname(r["name"])}_{_cname(f)}": ({pos}, {width}),')
    py.append("}")
    py.append('"""PERIPH_REG_FIELD -> (bit position, width)."""')
    py.append("IRQ: dict[str, int] = {")
    for name, n in irqs.items():
        py.append(f'    "{name}": {n},')
    py.append("}")
    py.append('"""Device interrupt line numbers (vector = 16 + line)."""')
    py.append("# fmt: on")
    py.append("")
    return "\n".join(h), "\n".join(py)


def write_outputs() -> int:
    crate = crate_dir()
    version = crate.name.split("-", 1)[1]
    header, pymap = render(generate(crate), version)
    HEADER.write_text(header)
    PYMAP.write_text(pymap)
    print(f"wrote {HEADER.relative_to(ROOT)} and {PYMAP.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(write_outputs())
