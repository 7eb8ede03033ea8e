"""Every protocol constant, generated from the DBC for Python and C.

The DBC (``config/can/fluxdrive.dbc``) is the one source of the protocol. This module turns
its numbers into named constants:

- every message (``BO_``): its arbitration id, ``ID_<MESSAGE>`` (Python only; the C side has
  cantools' ``FD_CAN_<MESSAGE>_FRAME_ID`` from the same DBC);
- every value table (``VAL_``) of a signal that carries the signal attribute ``ConstPrefix``:
  ``<PREFIX>_<NAME>`` per entry, ``<PREFIX>_CHOICES`` (value -> name) and ``<PREFIX>_COUNT`` (one
  past the largest value: the size of a table indexed by it). Signals sharing a prefix (the
  ``fault_code`` of FAULT and SAMPLE_FD, ``prm_id``/``pa_id``) must carry the same table;
  a value table without a prefix is an error, so a new table gets a name in the DBC;
- every integer network attribute (``BA_DEF_ ... INT``), CamelCase to UPPER_SNAKE:
  ``ProtocolVersion`` -> ``PROTOCOL_VERSION``, ``ArmKey`` -> ``ARM_KEY``, ...;
- C only: ``FD_INV_SCALE_<MESSAGE>_<SIGNAL>``, the reciprocal of every scaled integer
  signal's factor (the firmware's encoders multiply instead of dividing).

Python: the generated module ``fluxdrive/core/protocol_constants.py`` is committed (not built
at import) so that the engine's kernels (which may not import ``can``), mypy and ruff see plain
module-level ints, and importing the engine never parses the DBC; ``tests/test_protocol_gen.py``
fails when it differs from a regeneration. C: ``fd_protocol.h`` (prefix ``FD_``) is generated
into the firmware's build tree by ``firmware/codegen.cmake`` at every build, beside cantools'
codec.

This file imports only cantools and the standard library, so ``tools/gen_protocol.py`` (what
CMake runs) loads it without the engine::

    python tools/gen_protocol.py --python              # rewrite the committed Python module
    python tools/gen_protocol.py --c-header OUT.h [--dbc FILE]
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import cantools
from cantools.database.can import Database

_HERE = Path(__file__).resolve()
REPO_ROOT = _HERE.parents[4]
DBC_DEFAULT = REPO_ROOT / "config" / "can" / "fluxdrive.dbc"
PYTHON_MODULE = REPO_ROOT / "python" / "fluxdrive" / "core" / "protocol_constants.py"
PREFIX_ATTRIBUTE = "ConstPrefix"
GENERATED_MARK = "GENERATED from config/can/fluxdrive.dbc"
"""First-line mark of every generated file (the no-literal test skips them)."""

_NAME_RE = re.compile(r"^[A-Z][A-Z0-9_]*$")


class ProtocolGenError(ValueError):
    """The DBC cannot be turned into constants (the message says where)."""


@dataclass
class ValueTable:
    """One named value table: its prefix, entries (value -> NAME) and the signals carrying it."""

    prefix: str
    entries: dict[int, str]
    signals: list[str] = field(default_factory=list)


@dataclass
class ProtocolConstants:
    """What the DBC defines: message ids, value tables, integer attributes."""

    version: str
    message_ids: dict[str, int]
    tables: dict[str, ValueTable]
    attributes: dict[str, int]
    inv_scales: dict[str, float] = field(default_factory=dict)  # C only: <MSG>_<SIG>


def _upper_snake(camel: str) -> str:
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", camel).upper()


def _check_name(name: str, where: str) -> str:
    if not _NAME_RE.match(name):
        raise ProtocolGenError(f"{where}: {name!r} is not an UPPER_SNAKE identifier")
    return name


def extract(db: Database) -> ProtocolConstants:
    """The constants of a loaded DBC (raises :class:`ProtocolGenError` on an unnamed or
    inconsistent value table)."""
    ids: dict[str, int] = {}
    tables: dict[str, ValueTable] = {}
    inv_scales: dict[str, float] = {}
    for msg in sorted(db.messages, key=lambda m: m.frame_id):
        ids[_check_name(msg.name, f"BO_ {msg.frame_id}")] = int(msg.frame_id)
        for sig in msg.signals:
            if float(sig.scale) != 1.0 and not sig.is_float:
                inv_scales[f"{msg.name}_{sig.name.upper()}"] = 1.0 / float(sig.scale)
            if not sig.choices:
                continue
            where = f"VAL_ {msg.frame_id} {sig.name}"
            attrs = sig.dbc.attributes if sig.dbc is not None else {}
            prefix = str(attrs[PREFIX_ATTRIBUTE].value) if PREFIX_ATTRIBUTE in attrs else ""
            if not prefix:
                raise ProtocolGenError(
                    f"{where}: value table without a {PREFIX_ATTRIBUTE} attribute "
                    f'(add BA_ "{PREFIX_ATTRIBUTE}" SG_ {msg.frame_id} {sig.name} "NAME";)'
                )
            _check_name(prefix, where)
            entries = {int(v): _check_name(str(n), where) for v, n in sig.choices.items()}
            if prefix in tables:
                if tables[prefix].entries != entries:
                    raise ProtocolGenError(
                        f"{where}: prefix {prefix} already names a different table "
                        f"({', '.join(tables[prefix].signals)})"
                    )
                tables[prefix].signals.append(f"{msg.name}.{sig.name}")
            else:
                tables[prefix] = ValueTable(prefix, entries, [f"{msg.name}.{sig.name}"])
    attributes: dict[str, int] = {}
    if db.dbc is not None:
        for name, attr in db.dbc.attributes.items():
            if attr.definition.type_name == "INT":
                attributes[_upper_snake(name)] = int(attr.value)
    return ProtocolConstants(str(db.version or ""), ids, tables, attributes, inv_scales)


def load(dbc: str | Path = DBC_DEFAULT) -> ProtocolConstants:
    """Load a DBC (strict) and extract its constants."""
    db = cantools.database.load_file(str(dbc), database_format="dbc", strict=True)
    assert isinstance(db, Database)
    return extract(db)


def python_source(pc: ProtocolConstants) -> str:
    """The generated Python module's text."""
    out = [
        f'"""Protocol constants, {GENERATED_MARK} ({pc.version}) by',
        "``fluxdrive.can.protocol.generate``: do not edit; regenerate with",
        "``python tools/gen_protocol.py --python``. No imports.",
        '"""',
        "",
        "# ---- network attributes (BA_DEF_ INT)",
    ]
    for name, value in pc.attributes.items():
        out.append(f"{name} = {value}")
    out += ["", "# ---- message ids (BO_)"]
    for name, value in pc.message_ids.items():
        out.append(f"ID_{name} = 0x{value:03X}")
    for t in pc.tables.values():
        out += ["", f"# ---- {t.prefix}: {', '.join(t.signals)}"]
        for value, name in t.entries.items():
            out.append(f"{t.prefix}_{name} = {value}")
        out.append(f"{t.prefix}_CHOICES: dict[int, str] = {{")
        for value, name in t.entries.items():
            out.append(f'    {value}: "{name}",')
        out.append("}")
        out.append(f"{t.prefix}_COUNT = {max(t.entries) + 1}")
    return "\n".join(out) + "\n"


def c_header_text(pc: ProtocolConstants) -> str:
    """The generated C header's text (prefix ``FD_``)."""
    out = [
        f"/* Protocol constants, {GENERATED_MARK} ({pc.version}) by",
        " * tools/gen_protocol.py at build time: do not edit.",
        " * Message ids: FD_CAN_<MESSAGE>_FRAME_ID in fd_can.h (cantools, same DBC). */",
        "#ifndef FD_PROTOCOL_H",
        "#define FD_PROTOCOL_H",
        "",
        "/* network attributes (BA_DEF_ INT) */",
    ]
    for name, value in pc.attributes.items():
        out.append(f"#define FD_{name} {value}u")
    for t in pc.tables.values():
        out += ["", f"/* {t.prefix}: {', '.join(t.signals)} */", "enum {"]
        for value, name in t.entries.items():
            out.append(f"    FD_{t.prefix}_{name} = {value},")
        out.append(f"    FD_{t.prefix}_COUNT = {max(t.entries) + 1} /* one past the largest */")
        out.append("};")
    out += ["", "/* 1 / scale of every scaled signal: encoders multiply instead of dividing */"]
    for name, inv in pc.inv_scales.items():
        out.append(f"#define FD_INV_SCALE_{name} {float(f'{inv:.9g}')!r}f")
    out += ["", "#endif /* FD_PROTOCOL_H */"]
    return "\n".join(out) + "\n"


def _write_if_changed(path: Path, text: str) -> None:
    if not path.is_file() or path.read_text() != text:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def write_files(dbc: Path, python: bool, c_header: Path | None) -> None:
    """Regenerate the Python module (``python``) and/or the C header at ``c_header``
    (raises :class:`ProtocolGenError` or cantools' errors on a bad DBC)."""
    pc = load(dbc)
    if python:
        _write_if_changed(PYTHON_MODULE, python_source(pc))
    if c_header is not None:
        _write_if_changed(c_header, c_header_text(pc))
