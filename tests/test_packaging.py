"""Packaging: every import declared, the python version of the lock, resources found without
an editable checkout (FLUXDRIVE_ROOT) and refused in one line when they are not there."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import fluxdrive

REPO = Path(__file__).resolve().parents[1]
ENGINE = Path(fluxdrive.__file__).resolve().parent
# import name -> distribution name, where they differ
DIST = {"yaml": "pyyaml", "can": "python-can", "backports": "backports.zstd"}
# new in the standard library (zstd: 3.14), with a backport for older versions
STDLIB_LATER = {"compression"}


def _dist_name(req: str) -> str:
    for sep in ("[", ">", "<", "=", "!", "~", ";", " "):
        req = req.split(sep)[0]
    return req.strip().lower()


def test_every_import_of_the_package_is_a_declared_dependency():
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    declared = {_dist_name(r) for r in meta["dependencies"]}
    for reqs in meta["optional-dependencies"].values():
        declared |= {_dist_name(r) for r in reqs}
    imported: dict[str, str] = {}
    for f in sorted(ENGINE.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                mods = [node.module]
            else:
                continue
            for m in mods:
                top = m.split(".")[0]
                if (
                    top in sys.stdlib_module_names
                    or top in STDLIB_LATER
                    or top in ("fluxdrive", "__future__")
                ):
                    continue
                imported.setdefault(DIST.get(top, top).lower(), f"{f.relative_to(ENGINE)}")
    missing = {d: where for d, where in imported.items() if d not in declared}
    assert not missing, f"imported but not in pyproject.toml: {missing}"
    assert {"rosbags", "mcap", "cantools", "python-can"} <= declared


def test_requires_python_matches_the_lock():
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert meta["requires-python"] == ">=3.11"
    assert sys.version_info[:2] == (3, 11)  # the interpreter the lock was resolved for


def test_resources_found_outside_the_checkout_via_fluxdrive_root(tmp_path):
    """The package copied out of the checkout (as a wheel installs it) finds config/ through
    FLUXDRIVE_ROOT, and without it says so in one line instead of a traceback."""
    site = tmp_path / "site"
    shutil.copytree(ENGINE, site / "fluxdrive", ignore=shutil.ignore_patterns("__pycache__"))
    code = (
        "import sys\n"
        "from fluxdrive.core.machine import ConfigError\n"
        "from fluxdrive.drive.scenario import load_scenario, scenario_path\n"
        "from fluxdrive.can.protocol import default_dbc_path\n"
        "try:\n"
        "    sc = load_scenario(scenario_path('paper_2pct_150load'))\n"
        "except ConfigError as exc:\n"
        "    print(exc); sys.exit(2)\n"
        "assert default_dbc_path().is_file()\n"
        "print(sc.machine.name)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("FLUXDRIVE_ROOT", "PYTHONPATH")}
    env.update(PYTHONPATH=str(site), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = tmp_path / "elsewhere"
    run.mkdir()
    p = subprocess.run(
        [sys.executable, "-c", code], cwd=run, env=env, capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 2, p.stderr[-2000:]
    assert "FLUXDRIVE_ROOT" in p.stdout and len(p.stdout.strip().splitlines()) == 1
    assert "Traceback" not in p.stderr
    env["FLUXDRIVE_ROOT"] = str(REPO)
    p = subprocess.run(
        [sys.executable, "-c", code], cwd=run, env=env, capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 0, p.stdout + p.stderr[-2000:]
