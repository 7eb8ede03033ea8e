"""Where the package finds the project's files: config/ (machine cards, scenarios, the CAN
DBC), the message definitions (src/flux_drive_msgs/msg) and the output folders.

They live in the fluxdrive checkout, not inside the package, so one copy serves the engine,
the ROS nodes and the user.  The checkout is, in this order:
  1. $FLUXDRIVE_ROOT, when set (an installed, non-editable package points here);
  2. the checkout the package sits in (python/fluxdrive inside it: the editable install);
  3. the current directory, when it holds config/machines.
A file that is not there is refused with one line naming the path and FLUXDRIVE_ROOT.
This module imports nothing of the engine (fluxdrive/__init__.py uses it).
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT_ENV = "FLUXDRIVE_ROOT"


def _is_root(p: Path) -> bool:
    return (p / "config" / "machines").is_dir()


def find_root() -> Path:
    """The checkout the package reads its files from (see the module doc)."""
    env = os.environ.get(ROOT_ENV)
    if env:
        return Path(env).expanduser().resolve()
    here = Path(__file__).resolve().parents[3]  # <root>/python/fluxdrive/core/paths.py
    if _is_root(here):
        return here
    cwd = Path.cwd()
    if _is_root(cwd):
        return cwd
    return here


ROOT = find_root()
CONFIG_DIR = ROOT / "config"
MSG_DIR = ROOT / "src" / "flux_drive_msgs" / "msg"
DBC_PATH = CONFIG_DIR / "can" / "fluxdrive.dbc"


def project_file(path: Path, what: str) -> Path:
    """`path` if it exists, else a ConfigError that says where it was looked for and how to
    point the package at the checkout."""
    if path.exists():
        return path
    from fluxdrive.core.machine import ConfigError

    raise ConfigError(
        f"{what} not found at {path}: the package reads config/ and the message "
        f"definitions from the fluxdrive checkout ({ROOT}); set {ROOT_ENV} to "
        f"the checkout"
    )
