"""The repo explains itself: no code, doc or config points to a document outside the repo or to
an issue tracker number (what a maintainer needs is in docs/engine.md and docs/architecture.md)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# a reference to the design brief, or "issue 7" / "issue #7" / "#7" after the word issue
OUTSIDE = re.compile(r"\bBRIEF\b|\b[Ii]ssues? ?#?\d+\b")
TEXT_SUFFIXES = {
    ".py",
    ".md",
    ".yaml",
    ".yml",
    ".toml",
    ".cfg",
    ".sh",
    ".msg",
    ".srv",
    ".dbc",
    ".xml",
    ".txt",
    ".js",
    ".html",
    ".css",
}


def test_no_reference_outside_the_repo():
    files = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    hits = []
    for rel in files:
        p = ROOT / rel
        if p.suffix not in TEXT_SUFFIXES or not p.is_file() or rel.startswith("tests/test_repo_"):
            continue
        for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if OUTSIDE.search(line):
                hits.append(f"{rel}:{n}: {line.strip()[:100]}")
    assert not hits, "references outside the repo:\n" + "\n".join(hits)


def test_docs_the_code_points_to_exist():
    for name in ("engine.md", "architecture.md"):
        text = (ROOT / "docs" / name).read_text()
        assert len(text.splitlines()) > 50, name
    engine = (ROOT / "docs" / "engine.md").read_text()
    # the anchors the code cites
    for heading in (
        "## Timing convention",
        "## Observers",
        "## Metrics",
        "## PLL",
        "## Inverter",
        "## Default machine",
    ):
        assert heading in engine, heading
