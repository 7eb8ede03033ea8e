"""The ./fluxdrive script: Debian packages are set up only for the commands that use them
(the demo installs neither a browser nor the ARM toolchain), and a reader that goes away
ends the command quietly, never with a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _extras_for(*argv: str) -> str:
    """What the script hands the bootstrap for a command: run it with a bootstrap stand-in
    on a copy of the script (the real tools/ beside it is not touched)."""
    return subprocess.run(
        ["bash", "-c", _SCRIPT_PROBE, "probe", *argv],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
    ).stdout.strip()


# the script's own `case` block, cut out and run: the one place the choice is made
_SCRIPT_PROBE = r"""
block=$(sed -n '/^  case "${1:-}" in/,/^  case " \$\* "/p' ./fluxdrive)
eval "$block"
echo "$extras"
"""


def test_only_the_commands_that_use_them_install_debian_packages():
    assert _extras_for("test") == "browser arm"
    assert _extras_for("benchmark", "firmware") == "arm"
    assert _extras_for("bench", "--sil") == "arm"
    assert _extras_for("benchmark", "graph", "--scope-browser") == "browser arm"
    for cmd in ("demo", "run", "sim", "help", "replay"):
        assert _extras_for(cmd) == "", cmd


def test_bootstrap_fast_path_skips_extras_not_asked_for(tmp_path):
    """With nothing extra asked for, a checkout whose venv and workspace are current exits
    at once without looking for a browser or the toolchain (this checkout is current: the
    suite runs in it)."""
    env = dict(os.environ, FLUXDRIVE_BOOTSTRAP_EXTRAS="", PATH="/usr/bin:/bin")
    env.pop("FLUXDRIVE_BOOTSTRAP_FORCE", None)
    r = subprocess.run(
        ["bash", "-x", str(ROOT / "tools" / "bootstrap.sh")],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "chromium" not in "".join(
        line for line in r.stderr.splitlines(True) if line.startswith("+ command -v")
    )


def test_a_closed_pipe_ends_quietly():
    """`./fluxdrive help | true`: the reader is gone before the help is written."""
    env = dict(os.environ, FLUXDRIVE_SKIP_BOOTSTRAP="1")
    r = subprocess.run(
        f"'{sys.executable}' -m fluxdrive.cli help | true; echo \"rc=${{PIPESTATUS[0]}}\"",
        shell=True,
        executable="/bin/bash",
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
    )
    assert "Traceback" not in r.stderr, r.stderr
    assert r.stdout.strip() in ("rc=0", "rc=141")  # 141: cut short, as a shell filter
