"""Where a benchmark writes its figures: bench/results/ (the recorded runs, committed), or the folder named by
OMNIDATA_BENCH_RESULTS (the test suite's smoke runs, a trial run), so that a run that is not meant to be
recorded leaves the checkout as it was."""

from __future__ import annotations

import os
from pathlib import Path

RESULTS_ENV = "OMNIDATA_BENCH_RESULTS"
REPO = Path(__file__).resolve().parents[2]
# the committed figures: comparisons read them from here (a smoke run's folder is empty)
RECORDED = REPO / "bench" / "results"


def results_dir() -> Path:
    """The folder this run's results go to (created)."""
    folder = Path(os.environ.get(RESULTS_ENV) or RECORDED)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def results_path(name: str) -> Path:
    """The results file `name` (e.g. "render.json") of this run."""
    return results_dir() / name
