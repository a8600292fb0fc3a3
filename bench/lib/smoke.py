"""The smoke mode of the benchmarks that have no size knobs of their own: `--smoke` on the command line (or
OMNIDATA_BENCH_SMOKE=1) makes such a benchmark tiny (seconds), to prove that it still runs; its figures mean
nothing. Read at import, and put in the environment, so that the processes a benchmark spawns (which import it
afresh) are tiny too."""

from __future__ import annotations

import os
import sys

SMOKE_ENV = "OMNIDATA_BENCH_SMOKE"
SMOKE_HELP = "tiny sizes, seconds: proves the benchmark runs (its figures mean nothing)"

if "--smoke" in sys.argv:
    os.environ[SMOKE_ENV] = "1"
SMOKE = os.environ.get(SMOKE_ENV) == "1"
