"""`python -m tissuefit.cli ...`: the `tissuefit` command."""

import sys

from ._main import main

sys.exit(main())
