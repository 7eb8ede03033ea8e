"""Names from one place: outside the kernel modules that define the row layouts, a column of a
frame, truth, estimate or controller row is named by its layout constant (FR_*, TR_*, ES_*,
CO_*) or by the protocol's FRAME_INDEX, never by a raw number that breaks silently when a
layout grows. A layout array is one of ROW_NAMES, or any array the same file indexes in
its column by a layout constant or builds with a layout's width (`np.zeros((n, ES_N))`); a
layout row is one built with a layout's width alone (`np.zeros(FR_N)`) or a copy of one."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# where the layouts are defined and the kernels index them
KERNELS = {
    "python/fluxdrive/drive/plant.py",
    "python/fluxdrive/drive/observers.py",
    "python/fluxdrive/drive/control/kernel.py",
}
# names the code gives the rows of those layouts
ROW_NAMES = {"frames", "frame", "fr", "f", "truth", "est", "ctrl"}


def _name(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _has_literal(node: ast.expr) -> bool:
    if isinstance(node, ast.Constant):
        return type(node.value) is int
    if isinstance(node, ast.BinOp):
        return _has_literal(node.left) or _has_literal(node.right)
    return False


def _names_a_constant(node: ast.expr) -> bool:
    """The column is computed from a named constant (`FR_DA + (j + 1) % 3`)."""
    return any((_name(n) or "").isupper() for n in ast.walk(node))


def _layout_prefixes() -> tuple[str, ...]:
    """The prefix of every layout the kernel modules define (`_FR = Layout("FR")`: FR_SEQ,
    FR_N, ...): frames, truth, estimates, controller outputs, and the parameter, state,
    reference and drive rows (CP_, CS_, MP_, OP_, OS_, PS_, RF_, DR_, LD_)."""
    found = set()
    for rel in KERNELS:
        for node in ast.walk(ast.parse((REPO / rel).read_text())):
            if isinstance(node, ast.Call) and _name(node.func) == "Layout" and node.args:
                arg = node.args[0]
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                    found.add(arg.value + "_")
    return tuple(sorted(found))


# prefixes of the row layouts' constants (FR_SEQ, TR_T, ES_W, CO_MODE, CP_KP, FR_N, ...)
LAYOUT_PREFIXES = _layout_prefixes()


def _layout_constant(node: ast.AST) -> str | None:
    name = _name(node) if isinstance(node, (ast.Name, ast.Attribute)) else None
    return name if name is not None and name.startswith(LAYOUT_PREFIXES) else None


def layout_arrays(tree: ast.AST) -> set[str]:
    """Names of the file's layout arrays besides ROW_NAMES: indexed in their column by a
    layout constant somewhere (`a[:, FR_SEQ]`), or built with a layout's width
    (`a = np.zeros((n, ES_N))`)."""
    found = set(ROW_NAMES)
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Tuple):
            if any(_layout_constant(n) for n in ast.walk(node.slice.elts[-1])):
                found.add(_name(node.value) or "")
        elif isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
            if any((_layout_constant(n) or "").endswith("_N") for n in ast.walk(node.value)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                found |= {_name(t) or "" for t in targets}
    return found - {""}


def layout_rows(tree: ast.AST) -> set[str]:
    """Names of the file's one-row layout arrays: indexed by a layout constant somewhere
    (`cp[CP_KP]`), built with a layout's width alone (`f = np.zeros(FR_N)`), or a copy of
    one (`g = f.copy()`)."""
    found: set[str] = {
        _name(node.value) or ""
        for node in ast.walk(tree)
        if isinstance(node, ast.Subscript)
        and not isinstance(node.slice, ast.Tuple)
        and any(_layout_constant(n) for n in ast.walk(node.slice))
    }
    for _ in range(2):  # a copy of a row found on the first pass
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Assign, ast.AnnAssign)) or node.value is None:
                continue
            v = node.value
            if not isinstance(v, ast.Call):
                continue
            width = bool(v.args) and (_layout_constant(v.args[0]) or "").endswith("_N")
            copy = (
                isinstance(v.func, ast.Attribute)
                and v.func.attr == "copy"
                and _name(v.func.value) in found
            )
            if width or copy:
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                found |= {_name(t) or "" for t in targets}
    return found - {""}


def _literal_column(col: ast.expr) -> bool:
    """A column (or a slice of columns) given by a number, not by a named constant."""
    if isinstance(col, ast.Slice):
        ends = [e for e in (col.lower, col.upper) if e is not None]
        return any(_has_literal(e) for e in ends) and not any(_names_a_constant(e) for e in ends)
    return _has_literal(col) and not _names_a_constant(col)


def raw_column_indices(path: Path) -> list[str]:
    """`rows[..., 7]`, `frame[:, 3 + j]`: a layout array indexed in its column by a
    literal; `f[3:6]`, `f[10]`: a layout row likewise."""
    tree = ast.parse(path.read_text(), str(path))
    arrays = layout_arrays(tree)
    rows = layout_rows(tree)
    hits = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Subscript):
            continue
        cols = node.slice
        name = _name(node.value)
        if isinstance(cols, ast.Tuple):
            col = cols.elts[-1] if name in arrays else None
        else:
            col = cols if name in rows else None
        if col is not None and _literal_column(col):
            hits.add((node.lineno, f"{node.lineno}: {ast.unparse(node)}"))
    return [h for _, h in sorted(hits)]


def test_no_raw_column_index_outside_the_kernels():
    found = []
    for base in ("python", "src", "tests"):
        for f in sorted((REPO / base).rglob("*.py")):
            rel = f.relative_to(REPO).as_posix()
            if "/build/" in rel or "/install/" in rel or rel in KERNELS:
                continue
            found += [f"{rel}:{h}" for h in raw_column_indices(f)]
    assert found == [], "raw column indices (use the layout's constant):\n" + "\n".join(found)


def test_every_layout_is_checked():
    assert {"FR_", "TR_", "ES_", "CO_", "CP_", "CS_", "MP_", "OP_", "OS_"} <= set(LAYOUT_PREFIXES)


def test_the_check_sees_a_raw_index(tmp_path):
    f = tmp_path / "x.py"
    f.write_text(
        "a = frames[:, 12]\nb = est[-1, 3 + j]\nc = frames[:, FR_SEQ]\nd = frames[3]\n"
        "e = f[:, FR_DA + (j + 1) % 3]\n"
    )
    assert raw_column_indices(f) == ["1: frames[:, 12]", "2: est[-1, 3 + j]"]


def test_the_check_sees_a_raw_index_on_any_layout_array(tmp_path):
    f = tmp_path / "x.py"
    f.write_text(
        "a = np.zeros((n, ES_N))\nb = a[:, 2]\nc = q[:, CO_MODE]\nd = q[:, 4]\n"
        "e = xy[:, 1]\ng = a[3]\n"
    )
    assert raw_column_indices(f) == ["2: a[:, 2]", "4: q[:, 4]"]


def test_the_check_sees_a_raw_index_on_a_layout_row(tmp_path):
    f = tmp_path / "x.py"
    f.write_text(
        "r = np.zeros(FR_N)\na = r[3:6]\ng = r.copy()\ng[10] = 1.0\nb = r[FR_EN]\n"
        "c = r[FR_VAB : FR_VCA + 1]\nd = xs[2]\np = cfg.to_params(card)\nk = p[CP_KP]\n"
        "x = p[4]\n"
    )
    assert raw_column_indices(f) == ["2: r[3:6]", "4: g[10]", "10: p[4]"]
