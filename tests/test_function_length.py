"""Functions a reader can see whole: no function or method of the engine (python/) or of the
ROS packages (src/) is longer than MAX_LINES, except the numba kernels (their helpers stay
inlined: a call inside a per-sample kernel costs time, see docs/architecture.md).

KNOWN_LONG lists the functions still being taken apart, by "path::qualified name"; it only
shrinks: the test fails when a listed function has become short (delete its entry) and when an
unlisted one is long (split it into named steps)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 80
SKIP_DIRS = {"build", "install", "log", "__pycache__", ".ws", ".venv"}

KNOWN_LONG: set[str] = set()


def _is_kernel(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """A numba kernel: decorated with njit / jit / numba.njit(...) / a project alias of them."""
    for dec in fn.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in {"njit", "jit", "kernel", "vectorize", "guvectorize"}:
            return True
    return False


def _functions(tree: ast.Module):
    """(qualified name, node) of every function and method, nested ones included."""
    stack: list[tuple[str, ast.AST]] = [("", tree)]
    while stack:
        prefix, node = stack.pop()
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                stack.append((f"{prefix}{child.name}.", child))
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                qual = f"{prefix}{child.name}"
                yield qual, child
                stack.append((f"{qual}.", child))


def long_functions() -> dict[str, int]:
    """'path::qualname' -> length in lines, for every non-kernel function over MAX_LINES."""
    out: dict[str, int] = {}
    for root in ("python", "src"):
        for f in sorted((REPO / root).rglob("*.py")):
            rel = f.relative_to(REPO)
            if SKIP_DIRS & set(rel.parts):
                continue
            tree = ast.parse(f.read_text(), filename=str(rel))
            for qual, fn in _functions(tree):
                length = (fn.end_lineno or fn.lineno) - fn.lineno + 1
                if length > MAX_LINES and not _is_kernel(fn):
                    out[f"{rel.as_posix()}::{qual}"] = length
    return out


def test_no_function_over_80_lines_outside_kernels():
    found = long_functions()
    new = {k: v for k, v in found.items() if k not in KNOWN_LONG}
    assert not new, f"functions over {MAX_LINES} lines (split them into named steps): " + ", ".join(
        f"{k} ({v})" for k, v in sorted(new.items())
    )


def test_known_long_list_only_shrinks():
    found = long_functions()
    gone = sorted(k for k in KNOWN_LONG if k not in found)
    assert not gone, f"no longer over {MAX_LINES} lines: delete from KNOWN_LONG: {gone}"
