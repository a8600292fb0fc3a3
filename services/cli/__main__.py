"""`python -m services.cli ...`: the same entry point as the `omnidata` console script."""

import sys

from services.cli.main import main

sys.exit(main())
