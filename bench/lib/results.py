"""Where a benchmark writes its figures: bench/results/ (the recorded runs, committed), or the folder named by
OMNIDATA_BENCH_RESULTS (the test suite's smoke runs, a trial run), so that a run that is not meant to be
recorded leaves the checkout as it was."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

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


def add_run(path: Path, run: dict[str, Any], *, default_scenario: str | None = None) -> None:
    """Add `run` to the list of runs in `path`, keeping of its scenario (its "scenario" key) only the run
    before it, the one it is compared against; other scenarios' runs are left as they are."""
    runs = json.loads(path.read_text()) if path.exists() else []
    scenario = run.get("scenario", default_scenario)
    same = [r for r in runs if r.get("scenario", default_scenario) == scenario]
    kept = [r for r in runs if r.get("scenario", default_scenario) != scenario or r is same[-1]]
    path.write_text(json.dumps([*kept, run], indent=1) + "\n")
