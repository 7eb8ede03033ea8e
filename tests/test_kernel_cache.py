"""numba's disk cache is keyed on the kernels' sources only: every compiled kernel lives in
a package of `KERNEL_PACKAGES`, and an edit anywhere else (an experiment, the CLI) keeps the
key, so it costs no recompile."""

from __future__ import annotations

import ast
from pathlib import Path

import fluxdrive
from fluxdrive import KERNEL_PACKAGES, kernel_sources_hash

PKG = Path(fluxdrive.__file__).resolve().parent


def _compiles_kernels(path: Path) -> bool:
    """A module that imports numba (to decorate a kernel) or uses its decorators."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(
            a.name.split(".")[0] == "numba" for a in node.names
        ):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "numba":
            return True
    return False


def test_every_kernel_lives_in_a_kernel_package():
    outside = [
        str(f.relative_to(PKG))
        for f in sorted(PKG.rglob("*.py"))
        if f.relative_to(PKG).parts[0] not in KERNEL_PACKAGES
        and f.name != "__init__.py"
        and _compiles_kernels(f)
    ]
    assert not outside, f"numba kernels outside {KERNEL_PACKAGES}: {outside}"
    inside = [f for p in KERNEL_PACKAGES for f in (PKG / p).rglob("*.py") if _compiles_kernels(f)]
    assert inside, "no kernel module found: the scan is broken"


def test_key_follows_kernel_sources_not_the_rest(tmp_path, monkeypatch):
    """The key over a copy of the package: an edit to an experiment keeps it, an edit to a
    kernel module changes it."""
    import shutil

    copy = tmp_path / "fluxdrive"
    shutil.copytree(PKG, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(fluxdrive, "__file__", str(copy / "__init__.py"))
    key = kernel_sources_hash()
    exp = next((copy / "experiments").glob("*.py"))
    exp.write_text(exp.read_text() + "\n# an edit outside the kernels\n")
    assert kernel_sources_hash() == key
    kern = copy / "drive" / "plant.py"
    kern.write_text(kern.read_text() + "\n# an edit to a kernel module\n")
    assert kernel_sources_hash() != key
