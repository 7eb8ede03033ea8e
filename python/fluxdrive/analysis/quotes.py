"""Figures quoted in the README and docs/, filled in from generated results.

A quoted figure is written between two markers that name where it comes from::

    θ̃ RMS <!-- quote experiments/report.json experiments.fig14.data.rms_deg.flux_measured
    range:.2f -->2.65–2.67<!-- /quote -->°

- the file, relative to ``results/`` (JSON);
- a dotted path into it (list elements by index: ``a.b.0``);
- a format: ``.2f`` (any Python format spec) for one number, ``range:.2f`` for the smallest and
  the largest of a list ("2.65–2.67", or one number when they agree to the shown digits),
  ``len`` for the length of a list, ``str`` for the value as it is.

`fill(text)` rewrites every quote from the results; `stale(paths)` lists the files whose
quotes differ from what the results say (the docs test fails on any), and
``./fluxdrive docs quotes [--check]`` rewrites (or checks) the README and docs/*.md.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from fluxdrive.core.paths import ROOT

RESULTS = ROOT / "results"
QUOTE_RE = re.compile(
    r"<!-- quote (?P<file>\S+) (?P<path>\S+)\s+(?P<fmt>\S+) -->(?P<value>.*?)<!-- /quote -->",
    re.DOTALL,
)


class QuoteError(ValueError):
    """A quote names a file, key or format that does not exist."""


def _lookup(data: Any, path: str, where: str) -> Any:
    node = data
    for key in path.split("."):
        if isinstance(node, list) and key.isdigit() and int(key) < len(node):
            node = node[int(key)]
        elif isinstance(node, dict) and key in node:
            node = node[key]
        else:
            raise QuoteError(f"{where}: no '{key}' (of '{path}') in the results")
    return node


def format_value(value: Any, fmt: str, where: str = "quote") -> str:
    """One quoted figure as text (see the module docstring for the formats)."""
    try:
        if fmt == "str":
            return str(value)
        if fmt == "len":
            return str(len(value))
        if fmt.startswith("range:"):
            spec = fmt.split(":", 1)[1]
            lo, hi = (format(v, spec) for v in (min(value), max(value)))
            return lo if lo == hi else f"{lo}–{hi}"
        return format(value, fmt)
    except (TypeError, ValueError) as exc:
        raise QuoteError(f"{where}: cannot format {value!r} as '{fmt}' ({exc})") from None


class _Results:
    """JSON results files, each read once."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.cache: dict[str, Any] = {}

    def get(self, name: str, where: str) -> Any:
        if name not in self.cache:
            path = self.root / name
            try:
                self.cache[name] = json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                raise QuoteError(f"{where}: cannot read results file {path}: {exc}") from None
        return self.cache[name]


def fill(text: str, where: str = "text", results_dir: Path = RESULTS) -> str:
    """`text` with every quote's value replaced by what the results say."""
    results = _Results(results_dir)

    def one(m: re.Match[str]) -> str:
        line = text.count("\n", 0, m.start()) + 1
        at = f"{where}:{line}"
        value = _lookup(results.get(m["file"], at), m["path"], at)
        new = format_value(value, m["fmt"], at)
        return m.group(0).replace(f"-->{m['value']}<!--", f"-->{new}<!--", 1)

    return QUOTE_RE.sub(one, text)


def quoted_files(root: Path = ROOT) -> list[Path]:
    """The files whose quotes are kept current: README.md and docs/*.md."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def stale(paths: Iterable[Path], results_dir: Path = RESULTS) -> list[Path]:
    """The files whose quotes differ from the results."""
    return [p for p in paths if fill(p.read_text(), str(p), results_dir) != p.read_text()]


def count(paths: Iterable[Path]) -> int:
    """How many quotes the files hold."""
    return sum(len(QUOTE_RE.findall(p.read_text())) for p in paths)
