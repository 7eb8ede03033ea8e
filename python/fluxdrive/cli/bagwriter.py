"""`python -m fluxdrive.cli.bagwriter`: the recorder's bag-writing helper process
(fluxdrive.io.bagwriter): records on stdin, a bag out."""

from __future__ import annotations

import signal
import sys

from fluxdrive.io.bagwriter import write_stream


def main() -> int:
    # the recorder owns the run's end: its end marker or EOF finalises the bag
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return write_stream(sys.stdin.buffer)


if __name__ == "__main__":
    sys.exit(main())
