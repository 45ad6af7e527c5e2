"""`python -m mlaqc ...`: the `mlaqc` command line (mlaqc.cli)."""

import sys

from mlaqc.cli import main

sys.exit(main())
