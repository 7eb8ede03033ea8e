"""The house's habits, run with the suite: ruff lint, ruff format and mypy must be clean.

Each runs the tool the way a contributor does from the repo root (configuration in
pyproject.toml), so a finding here is exactly what `ruff check .`, `ruff format --check .` and
`mypy` print."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


def test_ruff_check_clean():
    r = _run("ruff", "check", "--no-cache", ".")
    assert r.returncode == 0, f"ruff check found problems:\n{r.stdout}{r.stderr}"


def test_ruff_format_clean():
    r = _run("ruff", "format", "--check", "--no-cache", ".")
    assert r.returncode == 0, (
        f"files not formatted (run `.venv/bin/ruff format .`):\n{r.stdout}{r.stderr}"
    )


def test_mypy_clean():
    r = _run("mypy")
    assert r.returncode == 0, f"mypy found problems:\n{r.stdout}{r.stderr}"
