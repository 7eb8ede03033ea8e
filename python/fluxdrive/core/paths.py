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


def check_output(path: Path | str, flag: str, kind: str = "dir", new: bool = False) -> Path:
    """An output path checked before any work starts: a folder (`kind="dir"`, may exist
    unless `new`) or a file (`kind="file"`, replaced if it exists) that can be written --
    the nearest existing folder on its way takes a probe file (this catches a read-only file
    system, a missing permission and a file in the way, whoever runs it).  Returns the path
    made absolute ('..' resolved as the shell would); ConfigError naming `flag` otherwise."""
    from fluxdrive.core.errors import ConfigError

    p = Path(os.path.abspath(Path(path).expanduser()))
    try:
        return _check_output(p, flag, kind, new)
    except OSError as exc:  # a name too long, a loop of links, ...
        raise ConfigError(f"{flag} {str(p)[:200]}: {exc.strerror or exc}") from None


def _check_output(p: Path, flag: str, kind: str, new: bool) -> Path:
    import tempfile

    from fluxdrive.core.errors import ConfigError

    if any(len(os.fsencode(part)) > 255 for part in p.parts):
        raise ConfigError(f"{flag} {str(p)[:200]}...: a name in it is longer than 255 bytes")
    if p.exists():
        if new:
            raise ConfigError(f"{flag} {p} exists already; choose a new one")
        if kind == "dir" and not p.is_dir():
            raise ConfigError(f"{flag} {p} is a file, not a folder")
        if kind == "file" and p.is_dir():
            raise ConfigError(f"{flag} {p} is a folder, not a file")
    probe_dir = p if p.is_dir() else p.parent
    while not probe_dir.exists() and probe_dir != probe_dir.parent:
        probe_dir = probe_dir.parent
    if not probe_dir.is_dir():
        raise ConfigError(f"{flag} {p}: {probe_dir} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".fluxdrive-probe-", dir=probe_dir)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ConfigError(f"{flag} {p}: cannot write in {probe_dir} ({exc.strerror})") from None
    return p
