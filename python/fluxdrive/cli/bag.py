"""`./fluxdrive bag recover BAG_DIR [--out DIR]`: a valid bag from one that was not finalised
(fluxdrive.io.bagrecover)."""

from __future__ import annotations

import sys
from pathlib import Path

from fluxdrive.core.machine import ConfigError
from fluxdrive.core.schema import Parser
from fluxdrive.io.bagrecover import is_finalised, mcap_file, recover, report


def main(argv: list[str]) -> int:
    ap = Parser(prog="fluxdrive bag", description="bag maintenance")
    sub = ap.add_subparsers(dest="cmd", required=True)
    rp = sub.add_parser(
        "recover",
        help="rebuild a valid bag from one that was not finalised (recorder killed, disk full)",
    )
    rp.add_argument("bag", type=Path, help="bag directory (or its .mcap file)")
    rp.add_argument("--out", type=Path, help="new bag directory (default <BAG>-recovered)")
    rp.add_argument(
        "--force", action="store_true", help="rewrite even a bag that was finalised properly"
    )
    args = ap.parse_args(argv)
    try:
        mcap = mcap_file(args.bag)
        if is_finalised(mcap) and not args.force:
            print(
                f"bag recover: {mcap.parent} was finalised properly (metadata.yaml, MCAP "
                f"footer); nothing to recover (--force rewrites it anyway)"
            )
            return 0
        rec = recover(args.bag, args.out)
    except (ConfigError, OSError) as exc:
        print(
            f"fluxdrive {exc}" if isinstance(exc, ConfigError) else f"fluxdrive bag recover: {exc}",
            file=sys.stderr,
        )
        return 2
    print(report(rec))
    return 0
