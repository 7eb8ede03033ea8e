"""One protocol source: every protocol constant is generated from the DBC.

- the committed Python module (``fluxdrive.core.protocol_constants``) equals a regeneration;
- the C header generates and names the same values;
- the ROS DriveFault message (an interface file rosidl builds, not generated) carries the
  DBC's engine fault codes;
- no protocol id or fault-code literal outside generated code: python/, src/ and firmware/
  are scanned (Python by its syntax tree, C by its text without comments) for protocol ids,
  fault codes and the other value-table entries written as numbers where the protocol is
  read or written, and for hand copies of generated names. The scanner is tested on planted
  snippets both ways, so a pass means something.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from fluxdrive.can.protocol import generate as gen
from fluxdrive.core import protocol_constants as pc

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("python", "src", "firmware")
SKIP_DIRS = {"build", ".ws", "__pycache__", "generated"}

CONSTANTS = gen.load()
GENERATED_NAMES = {n for n in vars(pc) if n.isupper()}
ID_FIELDS = {"arbitration_id", "frame_id", "can_id", "aid"}
MESSAGE_IDS = set(CONSTANTS.message_ids.values())


def _field_tables() -> dict[str, set[int]]:
    """Signal name -> the values of its table (signals with a value table)."""
    out: dict[str, set[int]] = {}
    db = gen.cantools.database.load_file(str(gen.DBC_DEFAULT), strict=True)
    for msg in db.messages:
        for sig in msg.signals:
            if sig.choices:
                out.setdefault(sig.name, set()).update(int(v) for v in sig.choices)
    for f in ID_FIELDS:
        out[f] = MESSAGE_IDS
    return out


FIELD_VALUES = _field_tables()
TABLE_NAMES = {t.prefix: list(t.entries.values()) for t in CONSTANTS.tables.values()}


@dataclass(frozen=True)
class Hit:
    path: str
    line: int
    what: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.what}"


# --------------------------------------------------------------------------- Python


def _int_literals(node: ast.AST) -> list[ast.Constant]:
    """Int literals a value expression stands for (a literal, a collection of them, the
    branches of ``a if c else b``)."""
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return [node]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        return []
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [c for e in node.elts for c in _int_literals(e)]
    if isinstance(node, ast.IfExp):
        return _int_literals(node.body) + _int_literals(node.orelse)
    return []


def _field_of(node: ast.AST) -> str | None:
    """The protocol field an expression reads: ``x.fault_code``, ``d["fault_code"]``,
    ``fault_code``, ``msg.arbitration_id`` ..."""
    name = None
    if isinstance(node, ast.Name):
        name = node.id
    elif isinstance(node, ast.Attribute):
        name = node.attr
    elif isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
        name = node.slice.value if isinstance(node.slice.value, str) else None
    elif isinstance(node, ast.Call) and node.args == [] and isinstance(node.func, ast.Name):
        name = None
    if name is None:
        return None
    for field in FIELD_VALUES:
        if name == field or name.endswith("_" + field):
            return field
    return None


def _is_hex(src: str, node: ast.Constant) -> bool:
    seg = ast.get_source_segment(src, node) or ""
    return seg.lower().startswith("0x")


def _bad(field: str, lits: list[ast.Constant]) -> list[ast.Constant]:
    return [c for c in lits if c.value in FIELD_VALUES[field]]


def scan_python(src: str, path: str) -> list[Hit]:
    """Protocol literals and hand copies in one Python source."""
    tree = ast.parse(src)
    hits: list[Hit] = []

    def hit(node: ast.AST, what: str) -> None:
        hits.append(Hit(path, getattr(node, "lineno", 0), what))

    for node in ast.walk(tree):
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                for n in ast.walk(t):
                    if isinstance(n, ast.Name) and n.id in GENERATED_NAMES:
                        hit(n, f"defines {n.id}, a generated protocol name")
        elif isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            fields = [f for f in map(_field_of, operands) if f]
            for f in fields:
                for o in operands:
                    for c in _bad(f, _int_literals(o)):
                        hit(c, f"{f} compared with the literal {c.value}")
        elif isinstance(node, ast.Dict):
            keys = [k for k in node.keys if k is not None]
            for k, v in zip(keys, node.values, strict=False):
                if isinstance(k, ast.Constant) and k.value in FIELD_VALUES:
                    for c in _bad(str(k.value), _int_literals(v)):
                        hit(c, f'"{k.value}": literal {c.value}')
            strs = [k.value for k in keys if isinstance(k, ast.Constant)]
            for prefix, names in TABLE_NAMES.items():
                named = [s for s in strs if s in names]
                if len(named) >= 3 and all(_int_literals(v) for v in node.values):
                    hit(node, f"a hand copy of the {prefix} table (names to numbers)")
        elif isinstance(node, ast.keyword) and node.arg in FIELD_VALUES:
            for c in _bad(node.arg, _int_literals(node.value)):
                hit(c, f"{node.arg}= literal {c.value}")
        elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            strs = [e.value for e in node.elts if isinstance(e, ast.Constant)]
            for prefix, names in TABLE_NAMES.items():
                if len(strs) >= 3 and strs == names[: len(strs)]:
                    hit(node, f"a hand copy of the {prefix} table (names in order)")
            hexids = [
                c
                for c in _int_literals(node)
                if isinstance(c.value, int) and c.value in MESSAGE_IDS and _is_hex(src, c)
            ]
            if len(hexids) >= 2 and any(c.value & (c.value - 1) for c in hexids):
                hit(node, f"message ids as literals: {[hex(c.value) for c in hexids]}")
    return hits


# --------------------------------------------------------------------------- C

_C_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*|\"(?:\\.|[^\"\\])*\"", re.S)
_C_INT = r"(0[xX][0-9a-fA-F]+|\d+)[uUlL]*\b"
_C_FIELD = re.compile(
    r"\b("
    + "|".join(sorted(FIELD_VALUES, key=len, reverse=True))
    + r")\s*(==|!=|=)(?!=)\s*"
    + _C_INT
)
_C_FIELD_LEFT = re.compile(
    r"(?<![\w.])"
    + _C_INT.replace(r"\b", "")
    + r"\s*(==|!=)\s*[\w.>-]*\b("
    + "|".join(sorted(FIELD_VALUES, key=len, reverse=True))
    + r")\b"
)
_C_DEFINE = re.compile(r"(?:#\s*define\s+|\b)(FD_[A-Z0-9_]+)\s*(?:=(?!=)\s*)?" + _C_INT)
_C_FRAME_ID = re.compile(r"(?:->|\.)id\s*(==|!=)\s*" + _C_INT)
_C_PARAM_CALL = re.compile(r"\bfd_core_param_(?:write|read)\s*\([^,()]+,\s*" + _C_INT)
_C_GENERATED = {"FD_" + n for n in GENERATED_NAMES if not n.startswith("ID_")}


def _c_int(text: str) -> int:
    return int(text, 0)


def scan_c(src: str, path: str) -> list[Hit]:
    """Protocol literals and hand copies in one C source (comments and strings removed)."""
    text = _C_COMMENT.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), src)
    hits: list[Hit] = []

    def line(pos: int) -> int:
        return text.count("\n", 0, pos) + 1

    for m in _C_FIELD.finditer(text):
        field, value = m.group(1), _c_int(m.group(3))
        if value in FIELD_VALUES[field]:
            hits.append(Hit(path, line(m.start()), f"{field} {m.group(2)} literal {value}"))
    for m in _C_FIELD_LEFT.finditer(text):
        value, field = _c_int(m.group(1)), m.group(3)
        if value in FIELD_VALUES[field]:
            hits.append(Hit(path, line(m.start()), f"literal {value} compared with {field}"))
    for m in _C_DEFINE.finditer(text):
        if m.group(1) in _C_GENERATED:
            hits.append(Hit(path, line(m.start()), f"defines {m.group(1)}, a generated name"))
    for m in _C_FRAME_ID.finditer(text):
        if _c_int(m.group(2)) in MESSAGE_IDS:
            hits.append(Hit(path, line(m.start()), f"frame id {m.group(1)} literal {m.group(2)}"))
    for m in _C_PARAM_CALL.finditer(text):
        if _c_int(m.group(1)) in FIELD_VALUES["prm_id"]:
            hits.append(Hit(path, line(m.start()), f"parameter id as the literal {m.group(1)}"))
    return hits


# --------------------------------------------------------------------------- the tree


def _sources() -> list[Path]:
    out = []
    for top in SCANNED:
        for p in sorted((ROOT / top).rglob("*")):
            if not p.is_file() or p.suffix not in (".py", ".c", ".h"):
                continue
            if SKIP_DIRS & set(p.relative_to(ROOT).parts):
                continue
            head = p.read_text(errors="replace")[:300]
            if gen.GENERATED_MARK in head:
                continue
            out.append(p)
    return out


def test_python_constants_equal_a_regeneration():
    text = (gen.PYTHON_MODULE).read_text()
    assert text == gen.python_source(CONSTANTS), (
        "fluxdrive/core/protocol_constants.py differs from the DBC: run "
        "python tools/gen_protocol.py --python"
    )


def test_c_header_names_the_dbc_values(tmp_path):
    out = tmp_path / "fd_protocol.h"
    run = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "gen_protocol.py"), "--c-header", str(out)],
        capture_output=True, text=True, check=False
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    text = out.read_text()
    assert f"#define FD_PROTOCOL_VERSION {pc.PROTOCOL_VERSION}u" in text
    assert f"FD_FAULT_WATCHDOG = {pc.FAULT_WATCHDOG}," in text
    assert f"FD_PRM_COUNT = {max(pc.PRM_CHOICES) + 1} " in text
    # every table entry, once
    for t in CONSTANTS.tables.values():
        for v, n in t.entries.items():
            assert text.count(f"FD_{t.prefix}_{n} = {v},") == 1


def test_generated_python_values_follow_the_dbc():
    db = gen.cantools.database.load_file(str(gen.DBC_DEFAULT), strict=True)
    for m in db.messages:
        assert getattr(pc, f"ID_{m.name}") == m.frame_id
    assert pc.PROTOCOL_VERSION == db.dbc.attributes["ProtocolVersion"].value
    table = db.get_message_by_name("FAULT").get_signal_by_name("fault_code").choices
    assert pc.FAULT_CHOICES == {int(k): str(v) for k, v in table.items()}


def test_unnamed_or_clashing_value_table_is_refused(tmp_path):
    dbc = gen.DBC_DEFAULT.read_text()
    unnamed = tmp_path / "unnamed.dbc"
    unnamed.write_text(dbc.replace('BA_ "ConstPrefix" SG_ 1792 st_state "ST";\n', ""))
    with pytest.raises(gen.ProtocolGenError, match="1792 st_state.*ConstPrefix"):
        gen.load(unnamed)
    clash = tmp_path / "clash.dbc"
    clash.write_text(dbc.replace('SG_ 1792 st_state "ST"', 'SG_ 1792 st_state "MODE"'))
    with pytest.raises(gen.ProtocolGenError, match="prefix MODE already names"):
        gen.load(clash)
    run = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "gen_protocol.py"), "--dbc", str(unnamed),
         "--c-header", str(tmp_path / "x.h")],
        capture_output=True, text=True, check=False
    )  # fmt: skip
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert "unnamed.dbc" in run.stderr and "Traceback" not in run.stderr


def test_drive_fault_message_carries_the_dbc_engine_codes():
    """DriveFault.msg is an interface file (rosidl); its constants must be the DBC's."""
    msg = (ROOT / "src" / "flux_drive_msgs" / "msg" / "DriveFault.msg").read_text()
    consts = dict(re.findall(r"^uint8\s+([A-Z_0-9]+)=(\d+)", msg, re.M))
    assert consts, "no constants found in DriveFault.msg"
    for name, value in consts.items():
        dbc_name = "NONE" if name == "FAULT_NONE" else name
        assert pc.FAULT_CHOICES.get(int(value)) == dbc_name, (name, value)


PLANTED_PY = """
FAULT_WATCHDOG = 9
ID_FAULT = 0x010
if msg.arbitration_id == 0x020: pass
if d["fault_code"] == 9: pass
if code.fault_code in (1, 9): pass
tx({"prm_id": 3, "mode": 1 if arm else 0})
m = can.Message(arbitration_id=0x700)
ids = {i: [] for i in (0x080, 0x100, 0x101)}
PARAMS = {"CUR_KP": 1, "CUR_KI": 2, "L_HAT": 3}
STATUS = ("OK", "UNKNOWN_PARAM", "OUT_OF_RANGE")
"""
CLEAN_PY = """
x = 16
if n == 16 and mask & 0x80: pass
for i in range(16): pass
if d["fault_code"] == FAULT_WATCHDOG: pass
if msg.arbitration_id == ID_ARM_MODE: pass
if m["mode"] == 7: pass
sizes = (0x10, 0x20)
"""
PLANTED_C = """
#define FD_ARM_KEY 0xA5u
enum { FD_FAULT_WATCHDOG = 9 };
CHECK(last_fault.fault_code == 9);
c->fault_code = 0;
if (f->id == 0x020) {}
if (1 == s.mode) {}
CHECK(fd_core_param_write(&core, 3, 1.0f) == FD_PA_OK);
"""
CLEAN_C = """
/* fault_code == 9 in a comment */
CHECK(last_fault.fault_code == FD_FAULT_WATCHDOG);
c->fault_code = (uint8_t)FD_FAULT_NONE;
if (c->k == 16u) {}
#define FD_CMD_SLOTS 8u
CHECK(fd_core_param_write(&core, FD_PRM_L_HAT, 1.0f) == FD_PA_OK);
puts("fault_code = 9");
"""


def test_scanner_flags_planted_literals_and_passes_clean_code():
    py = scan_python(PLANTED_PY, "planted.py")
    assert sorted({h.line for h in py}) == list(range(2, 12)), "\n".join(map(str, py))
    assert scan_python(CLEAN_PY, "clean.py") == []
    c = scan_c(PLANTED_C, "planted.c")
    assert sorted({h.line for h in c}) == list(range(2, 9)), "\n".join(map(str, c))
    assert scan_c(CLEAN_C, "clean.c") == []


def test_no_protocol_literal_outside_generated_code():
    hits: list[Hit] = []
    files = _sources()
    assert len(files) > 50
    for p in files:
        rel = str(p.relative_to(ROOT))
        src = p.read_text()
        hits += scan_python(src, rel) if p.suffix == ".py" else scan_c(src, rel)
    assert not hits, "protocol literals (use the generated names):\n" + "\n".join(map(str, hits))
