"""`./fluxdrive fault-matrix [--write DOC]`: the fault-injection matrix of the control path
(fluxdrive.drive.faultmatrix), printed or written into its generated block in DOC."""

from __future__ import annotations

import sys
from pathlib import Path

from fluxdrive.core.schema import Parser
from fluxdrive.drive import faultmatrix
from fluxdrive.drive.faultmatrix import run_matrix, table, write_doc


def main(argv: list[str] | None = None) -> int:
    ap = Parser(
        prog="fluxdrive fault-matrix", description=(faultmatrix.__doc__ or "").split("\n\n")[0]
    )
    ap.add_argument(
        "--write",
        type=Path,
        metavar="DOC",
        help="replace the generated table in DOC (e.g. docs/safety.md)",
    )
    args = ap.parse_args(argv)
    rows = run_matrix(progress=True)
    text = table(rows)
    if args.write:
        write_doc(args.write, text)
        print(f"wrote the table into {args.write}", file=sys.stderr)
    else:
        print(text, end="")
    bad = [r["fault"] for r in rows if not r["ok"]]
    if bad:
        print(f"fault-matrix: unexpected outcome for {', '.join(bad)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
