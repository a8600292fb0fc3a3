"""Helpers of the A/B benchmarks: a module of the project as it was at a git revision, loaded beside today's;
two serving processes, one of a revision's checkout and one of today's, asked in lockstep; and a results file
written with the previous run kept."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
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


@contextmanager
def lockstep_sides(rev: str, serve: str, argv: list[str]) -> Iterator[dict[str, subprocess.Popen[str]]]:
    """{"before": a process serving REV's checkout, "after": one serving this checkout}: each runs the Python
    source `serve` with (its checkout's root, *argv) and has printed "ready"; the caller writes requests to
    their stdin and reads answers from their stdout. Both are ended (stdin closed, waited for) on exit."""
    with tempfile.TemporaryDirectory(prefix="omnidata-ab-") as tmp:
        archive = subprocess.run(["git", "archive", rev], cwd=ROOT, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        sides = {side: subprocess.Popen([sys.executable, "-c", serve, root, *argv], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True)
                 for side, root in (("before", tmp), ("after", str(ROOT)))}
        try:
            for proc in sides.values():
                if proc.stdout is None or proc.stdout.readline().strip() != "ready":
                    raise RuntimeError("a side of the A/B did not start")
            yield sides
        finally:
            for proc in sides.values():
                if proc.stdin is not None:
                    proc.stdin.close()
                proc.wait()


def write_keeping_before(path: Path, result: dict) -> None:
    """Write `result` to the JSON file `path`, the run it replaces kept under "before" (one level deep)."""
    if path.exists():
        result["before"] = {k: v for k, v in json.loads(path.read_text()).items() if k != "before"}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1) + "\n")
