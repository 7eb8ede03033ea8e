"""`python -m fluxdrive.cli`: the ./fluxdrive command line."""

import os
import sys

from fluxdrive.cli.main import main


def _run() -> int:
    try:
        code = main()
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        # the reader of our output went away (`./fluxdrive topic echo ... | head`): end
        # quietly as a filter does, not with a traceback; stdout is pointed at /dev/null so
        # the interpreter's own flush at exit does not raise again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a filter cut short


sys.exit(_run())
