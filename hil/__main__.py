"""`python -m hil` runs the `hil` command (used by tests to start `hil sim` as a subprocess)."""

import sys

from hil.cli import main

sys.exit(main())
