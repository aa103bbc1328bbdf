"""python -m physgrad: the console script `physgrad` (run, compare, report, check)."""

import sys

from physgrad.cli import main

sys.exit(main())
