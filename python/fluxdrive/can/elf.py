"""The one ELF reader of the firmware tools: the images' loadable segments and symbols
(the virtual board loads the segments, the cost model and the interrupt trace look symbols
up), and the Thumb instruction boundaries of a block of code."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import NamedTuple

from fluxdrive.can.firmware import FirmwareBuildError

__all__ = ["ElfSymbol", "elf_symbols", "function_ranges", "read_elf", "thumb_pcs"]


class ElfSymbol(NamedTuple):
    """An ELF symbol: value (Thumb functions: address | 1), size [bytes], a function?"""

    value: int
    size: int
    function: bool


def read_elf(path: Path) -> tuple[bytes, list[tuple[int, int, int]], dict[str, ElfSymbol]]:
    """(file bytes, PT_LOAD segments (paddr, offset, filesz), symbols by name) of a 32-bit
    little-endian ELF: what the virtual board loads and the cost model looks up."""
    b = path.read_bytes()
    if b[:4] != b"\x7fELF" or b[4] != 1 or b[5] != 1:
        raise FirmwareBuildError(f"{path}: not a 32-bit little-endian ELF")
    phoff, shoff = struct.unpack_from("<II", b, 28)
    phentsize, phnum, shentsize, shnum = struct.unpack_from("<HHHH", b, 42)
    segs = []
    for i in range(phnum):
        p_type, p_off, _vaddr, p_paddr, p_filesz = struct.unpack_from(
            "<IIIII", b, phoff + i * phentsize
        )
        if p_type == 1 and p_filesz > 0:
            segs.append((p_paddr, p_off, p_filesz))
    syms: dict[str, ElfSymbol] = {}
    for name, sym in _symtab(b, shoff, shentsize, shnum):
        syms[name] = sym
    return b, segs, syms


def _symtab(b: bytes, shoff: int, shentsize: int, shnum: int) -> list[tuple[str, ElfSymbol]]:
    """Every entry of the ELF's symbol table, in order (names may repeat: static functions)."""
    secs = [struct.unpack_from("<IIIIIIIIII", b, shoff + i * shentsize) for i in range(shnum)]
    out = []
    for s in secs:
        if s[1] != 2:  # SHT_SYMTAB
            continue
        strtab = secs[s[6]]
        for j in range(s[5] // 16):
            name, value, size, info, _other, _shndx = struct.unpack_from(
                "<IIIBBH", b, s[4] + 16 * j
            )
            end = b.index(b"\0", strtab[4] + name)
            sym = ElfSymbol(value, size, info & 0xF == 2)  # STT_FUNC
            out.append((b[strtab[4] + name : end].decode(), sym))
    return out


def function_ranges(path: Path) -> list[tuple[int, int, str]]:
    """(start, end, name) of every function symbol with a size, by address."""
    b = path.read_bytes()
    shoff = struct.unpack_from("<I", b, 32)[0]
    shentsize, shnum = struct.unpack_from("<HH", b, 46)
    return sorted(
        (s.value & ~1, (s.value & ~1) + s.size, name)
        for name, s in _symtab(b, shoff, shentsize, shnum)
        if s.function and s.size > 0
    )


def elf_symbols(path: Path) -> dict[str, ElfSymbol]:
    """Symbol name -> :class:`ElfSymbol` of an ELF."""
    return read_elf(path)[2]


def thumb_pcs(address: int, code: bytes) -> list[int]:
    """Addresses of the Thumb instructions of a block of code starting at ``address`` (a
    32-bit one starts with 0b11101, 0b11110 or 0b11111)."""
    out, i = [], 0
    while i + 1 < len(code):
        out.append(address + i)
        hw = code[i] | (code[i + 1] << 8)
        i += 4 if (hw & 0xF800) in (0xE800, 0xF000, 0xF800) else 2
    return out
