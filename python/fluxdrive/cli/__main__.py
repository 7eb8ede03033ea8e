"""`python -m fluxdrive.cli`: the ./fluxdrive command line."""

import sys

from fluxdrive.cli.main import main

sys.exit(main())
