"""Exact pins of what pip installed in this interpreter, for requirements.lock.

    python tools/freeze_lock.py                 print `name==version` for every pip-installed
                                                distribution (tools/lock.sh writes the lock)
    python tools/freeze_lock.py --stale LOCK    print names pip installed that LOCK does not pin
                                                (tools/bootstrap.sh uninstalls them)

`pip freeze` cannot be used as is: the ROS wheels carry egg-info directories of their inner
Python packages (rclpy, std_msgs, rosidl_parser, ...), which pip freeze lists but which are
not installable distributions. Only distributions whose INSTALLER is pip count here, and the
project itself (installed editable) is left out.
"""

import importlib.metadata as md
import re
import sys

EXCLUDE = {"fluxdrive"}


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def installed_pins() -> dict[str, str]:
    pins = {}
    for dist in md.distributions():
        if (dist.read_text("INSTALLER") or "").strip() != "pip":
            continue
        name = dist.metadata["Name"]
        if norm(name) not in EXCLUDE:
            pins[norm(name)] = f"{name}=={dist.version}"
    return pins


def locked_names(path: str) -> set[str]:
    names = set()
    with open(path) as f:
        for line in f:
            line = line.split("#")[0].strip()
            if line:
                names.add(norm(re.split(r"[=<>!~\[; ]", line)[0]))
    return names


def main(argv: list[str]) -> int:
    pins = installed_pins()
    if argv[:1] == ["--stale"] and len(argv) == 2:
        locked = locked_names(argv[1])
        for key in sorted(pins):
            if key not in locked:
                print(pins[key].split("==")[0])
        return 0
    if argv:
        print(__doc__, file=sys.stderr)
        return 2
    sys.stdout.write("".join(pins[k] + "\n" for k in sorted(pins)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
