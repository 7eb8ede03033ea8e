"""Names from one place: outside the kernel modules that define the row layouts, a column of a
frame, truth, estimate or controller row is named by its layout constant (FR_*, TR_*, ES_*,
CO_*) or by the protocol's FRAME_INDEX, never by a raw number that breaks silently when a
layout grows."""

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


def raw_column_indices(path: Path) -> list[str]:
    """`rows[..., 7]`, `frame[:, 3 + j]`: a row array indexed in its column by a literal."""
    hits = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Subscript) and _name(node.value) in ROW_NAMES:
            cols = node.slice
            col = cols.elts[-1] if isinstance(cols, ast.Tuple) else None
            if col is not None and _has_literal(col) and not _names_a_constant(col):
                hits.append(f"{node.lineno}: {ast.unparse(node)}")
    return hits


def test_no_raw_column_index_outside_the_kernels():
    found = []
    for base in ("python", "src", "tests"):
        for f in sorted((REPO / base).rglob("*.py")):
            rel = f.relative_to(REPO).as_posix()
            if "/build/" in rel or "/install/" in rel or rel in KERNELS:
                continue
            found += [f"{rel}:{h}" for h in raw_column_indices(f)]
    assert found == [], "raw column indices (use the layout's constant):\n" + "\n".join(found)


def test_the_check_sees_a_raw_index(tmp_path):
    f = tmp_path / "x.py"
    f.write_text(
        "a = frames[:, 12]\nb = est[-1, 3 + j]\nc = frames[:, FR_SEQ]\nd = frames[3]\n"
        "e = f[:, FR_DA + (j + 1) % 3]\n"
    )
    assert raw_column_indices(f) == ["1: frames[:, 12]", "2: est[-1, 3 + j]"]
