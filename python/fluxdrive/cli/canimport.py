"""`./fluxdrive can-import LOG --out BAG`: a CAN capture (.log/.asc/.blf/.trc) into a bag of
PhaseFrames (fluxdrive.io.canimport)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from fluxdrive.can.protocol import LinkOptions
from fluxdrive.core.schema import Parser, option
from fluxdrive.io.canimport import PHASE_FRAME_TOPIC, import_capture


def main(argv: list[str] | None = None) -> int:
    """CLI: ``can-import LOG --out BAG [--topic T] [--scenario S] [--decimation D]``;
    prints counts, last line JSON.  Exit 2: nothing imported (one line why); 1: imported,
    but the capture is truncated (the bag holds the frames before the cut, and says so in
    its metadata); 0: imported whole."""
    ap = Parser(
        prog="fluxdrive can-import",
        description="CAN capture (.log/.asc/.blf) -> bag of PhaseFrames",
    )
    ap.add_argument("log", help="capture file: candump .log, Vector .asc or .blf")
    ap.add_argument("--out", required=True, help="output bag directory (must not exist)")
    ap.add_argument("--topic", default=PHASE_FRAME_TOPIC)
    ap.add_argument(
        "--scenario",
        help="scenario the bench ran: its machine card and observer "
        "configurations go into the bag (default: the default machine card)",
    )
    option(
        ap,
        "--decimation",
        LinkOptions,
        default=None,
        help="PWM periods per sample (default: the capture's sequence-counter step)",
    )
    a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    if Path(a.out).exists():
        print(f"can-import: {a.out} exists; choose a new bag directory", file=sys.stderr)
        return 2
    try:
        res = import_capture(
            a.log, a.out, topic=a.topic, scenario=a.scenario, decimation=a.decimation
        )
    except (ValueError, OSError) as exc:  # CaptureError, ConfigError: one line
        # (the first line only: a message is one line; `!r` would quote it)
        why = str(exc).splitlines()[0] if str(exc) else repr(exc)
        print(f"can-import: {why}", file=sys.stderr)
        return 2
    bad = res.get("malformed_lines", 0)
    if bad:
        print(
            f"[can-import] skipped {bad} malformed line(s): "
            + "; ".join(res["first_malformed_lines"]),
            file=sys.stderr,
        )
    print(
        f"[can-import] {res['decoded']} sample frames decoded ({res['layout']}, D = "
        f"{res['decimation']}, sample period {res['sample_period_s'] * 1e3:g} ms), "
        f"{res['malformed']} malformed, {res['gaps']} gaps, {res['duplicates']} duplicates, "
        f"{res['out_of_order']} out of order, {res['jumps']} jumps (left out) -> "
        f"{res['written']} PhaseFrames "
        f"on {a.topic} in {a.out}",
        file=sys.stderr,
    )
    print(json.dumps(res))
    if res.get("truncated"):
        print(
            f"can-import: WARNING: {a.log}: {res['truncated']}; the bag holds the "
            f"{res['written']} sample frames before it",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
