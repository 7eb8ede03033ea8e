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
    """mypy over the engine and the ROS packages (pyproject's `files`: python and src), every
    module of both: the count it reports is the count of their .py files (setup.py and
    colcon's build/install/log folders aside, as pyproject excludes them)."""
    r = _run("mypy")
    assert r.returncode == 0, f"mypy found problems:\n{r.stdout}{r.stderr}"

    def checked(p: Path) -> bool:  # pyproject's exclude
        parts = p.relative_to(REPO).parts
        return p.name != "setup.py" and not (
            parts[0] == "src" and parts[2] in ("build", "install", "log")
        )

    files = [p for root in ("python", "src") for p in (REPO / root).rglob("*.py") if checked(p)]
    assert {"python", "src"} == {p.relative_to(REPO).parts[0] for p in files}
    assert f"no issues found in {len(files)} source files" in r.stdout, r.stdout
