"""Protocol constants from the DBC (fluxdrive.can.protocol.generate), for the firmware build
and for regenerating the committed Python module.

    python tools/gen_protocol.py --python      # rewrite fluxdrive/core/protocol_constants.py
    python tools/gen_protocol.py --c-header OUT.h [--dbc FILE]

The generator is loaded by its file path, so this needs only cantools (CMake runs it with
the project's Python before the engine is importable).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

GENERATOR = Path(__file__).resolve().parents[1] / "python/fluxdrive/can/protocol/generate.py"


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("fluxdrive_protocol_generate", GENERATOR)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main(argv: Sequence[str] | None = None) -> int:
    gen = _generator()
    ap = argparse.ArgumentParser(
        prog="gen_protocol.py", description="protocol constants from the DBC, for Python and C"
    )
    ap.add_argument("--dbc", type=Path, default=gen.DBC_DEFAULT, help="the protocol DBC")
    ap.add_argument("--python", action="store_true", help=f"rewrite {gen.PYTHON_MODULE.name}")
    ap.add_argument("--c-header", type=Path, metavar="OUT", help="write the C header here")
    a = ap.parse_args(argv)
    if not a.python and a.c_header is None:
        ap.error("nothing to do: give --python and/or --c-header OUT")
    if not a.dbc.is_file():
        print(f"gen_protocol.py: --dbc {a.dbc}: no such file", file=sys.stderr)
        return 2
    try:
        gen.write_files(a.dbc, a.python, a.c_header)
    except Exception as e:  # one line naming the file, whatever cantools raised
        print(f"gen_protocol.py: {a.dbc}: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
