"""Benchmarks (bench/README.md). The `omnidata` commands a benchmark runs start cold unless it says otherwise:
a warm-start server (services.cli.warm_start) would let its later runs skip the start-up they measure.
bench/render/warm_start.py compares the two."""

import os

os.environ.setdefault("OMNIDATA_WARM_START", "0")
