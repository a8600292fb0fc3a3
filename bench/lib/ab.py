"""Helpers of the A/B benchmarks: a module of the project as it was at a git revision, loaded beside today's,
and a results file written with the previous run kept."""

from __future__ import annotations

import importlib.util
import json
import subprocess
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]


def module_at(rev: str, relpath: str, folder: Path) -> ModuleType:
    """The file `relpath` (e.g. services/worker/inputs/curvature.py) at git revision `rev`, written to
    `folder` and loaded as a module of its own; its numba kernels are compiled in this process, not cached
    (the A/B's first call, outside the timing, compiles them). Its imports of the project resolve to today's
    modules."""
    source = subprocess.run(["git", "show", f"{rev}:{relpath}"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout
    path = folder / f"{Path(relpath).stem}_{rev.replace('/', '_')}.py"
    path.write_text(source.replace("cache=True", "cache=False"))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write_keeping_before(path: Path, result: dict) -> None:
    """Write `result` to the JSON file `path`, the run it replaces kept under "before" (one level deep)."""
    if path.exists():
        result["before"] = {k: v for k, v in json.loads(path.read_text()).items() if k != "before"}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1) + "\n")
