"""`./fluxdrive benchmark setup [--write] [--pip-cache]`: how long the first use takes.

The checkout's committed tree (git archive HEAD) is exported into a fresh temporary folder and
its `./fluxdrive help` run there: the whole first-use set-up the demo gets (`tools/bootstrap.sh`
with the demo's extras: a new `.venv` with requirements.lock, the ROS wheels' CMake repair,
the colcon build of `src/`), timed; then once more, the no-op check every later command pays.
pip runs without its download cache (PIP_NO_CACHE_DIR=1: every wheel downloaded, as on a fresh
machine) unless --pip-cache.  The Debian packages the bootstrap installed (it says so on
stderr) are listed: the demo's first use installs none.  With --write the record goes to
results/benchmarks/setup.json, which the README quotes.  Last line JSON."""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import Parser

# what the bootstrap's stderr says when it installs a Debian package (tools/bootstrap.sh)
APT_LINE = re.compile(r"installing Debian's (.+?) for ")
# what the bootstrap says when the colcon build is done (tools/bootstrap.sh)
COLCON_LINE = re.compile(r"workspace built in (\d+) s")
# environment a checkout's own shell may carry that would skip or redirect the set-up
_CLEARED = (
    "FLUXDRIVE_SKIP_BOOTSTRAP",
    "FLUXDRIVE_ROOT",
    "FLUXDRIVE_PYTHON",
    "VIRTUAL_ENV",
    "PYTHONPATH",
)


def _fresh_env(pip_cache: bool) -> dict[str, str]:
    """This environment without what points at this checkout (its variables, its .venv and
    .ws on PATH), so the fresh tree finds the machine's own python3.11 as a new user would."""
    env = {k: v for k, v in os.environ.items() if k not in _CLEARED}
    mine = (str(ROOT / ".venv"), str(ROOT / ".ws"))
    path = [p for p in env.get("PATH", "").split(os.pathsep) if p and not p.startswith(mine)]
    env["PATH"] = os.pathsep.join(path)
    if not pip_cache:
        env["PIP_NO_CACHE_DIR"] = "1"
    return env


def _timed_help(tree: Path, env: dict[str, str], timeout_s: float) -> tuple[float, str]:
    """Wall seconds of `./fluxdrive help` in `tree` and its stderr; SystemExit on a failure."""
    t0 = time.perf_counter()
    p = subprocess.run(
        ["./fluxdrive", "help"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    wall = time.perf_counter() - t0
    if p.returncode:
        tail = "\n".join(p.stderr.strip().splitlines()[-15:])
        raise SystemExit(f"benchmark setup: ./fluxdrive help failed in {tree}:\n{tail}")
    return wall, p.stderr


def bench_setup(argv: list[str]) -> dict[str, Any]:
    ap = Parser(prog="fluxdrive benchmark setup", description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true", help="write results/benchmarks/setup.json")
    ap.add_argument(
        "--pip-cache", action="store_true", help="let pip use its download cache (not fresh)"
    )
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per step")
    args = ap.parse_args(argv)
    from fluxdrive.cli.bench import _export_commit, _ref_commit, write_benchmark

    sha = _ref_commit("HEAD", ROOT)
    env = _fresh_env(args.pip_cache)
    with tempfile.TemporaryDirectory(prefix="fluxdrive-setup-") as tmp:
        tree = Path(tmp) / "fluxdrive"
        tree.mkdir()
        _export_commit(sha, ROOT, tree)
        print(f"[setup] first use in a fresh export of {sha[:10]}: {tree}", flush=True)
        first, log = _timed_help(tree, env, args.timeout)
        print(f"[setup] first use: {first:.0f} s", flush=True)
        again, _ = _timed_help(tree, env, args.timeout)
        print(f"[setup] every later use: {again:.2f} s", flush=True)
    apt = [pkg for m in APT_LINE.finditer(log) for pkg in m.group(1).split()]
    colcon = COLCON_LINE.search(log)
    res = {
        "commit": sha,
        "first_use_s": round(first, 1),
        "first_use_min": round(first / 60.0, 2),
        "later_use_s": round(again, 2),
        "pip_download_cache": bool(args.pip_cache),
        "debian_packages_installed": apt,
        "colcon_build_s": int(colcon.group(1)) if colcon else None,
        "cpus": os.cpu_count(),
    }
    if args.write:
        write_benchmark("setup", res)
    return res
