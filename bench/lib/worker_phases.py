"""Where a local worker's CPU goes per view in a real `omnidata generate` (room_cost.py --phases).

ENTRY, run by python with this file's path and generate's arguments (PYTHONPATH the checkout measured,
PHASES_DIR set), runs `omnidata generate` with its forked worker's TaskRunner timed around its parts: each
task's `make` (the cue's derivation and encoding), the render, the store's put_many, the claims and the done
record, the whole `run` of a message, and the worker's CPU between runs (its serve loop: reading messages,
sending outcomes, the heartbeat thread). Clocks: process CPU (time.process_time: every thread of the worker,
the store's flushing threads included) and wall. The worker writes PHASES_DIR/<pid>.json after every message.
Nothing here loads numpy before generate pins its threads, so its worker is forked and keeps the timing.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

ENV = "PHASES_DIR"
# (module, class, method) timed as a phase of a message's run
PHASES = (
    ("services.worker.run.runner", "TaskRunner", "render_view"),
    ("services.worker.run.results", "BatchResults", "compute"),
    ("services.core.storage.local", "LocalStore", "put_many"),
    ("services.worker.run.claim", "TaskLedger", "claim"),
    ("services.worker.run.claim", "TaskLedger", "claim_view_rest"),
    ("services.worker.run.claim", "TaskLedger", "record_done_many"),
)


def install(folder: Path) -> None:
    """Time this process's TaskRunner (module docstring); records go to folder/<pid>.json."""
    import importlib

    from services.worker.run.runner import TaskRunner

    folder.mkdir(parents=True, exist_ok=True)
    rec: dict = {"make": [], "phases": [], "runs": []}  # [run index, name, CPU s, wall s]; runs: CPU spans

    def timed(fn, name: str, table: str, named=None):  # noqa: ANN001, ANN202
        def wrapper(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                return fn(self, *a, **k)
            finally:
                rec[table].append([len(rec["runs"]), named(a) if named else name,
                                   time.process_time() - c0, time.perf_counter() - w0])
        return wrapper

    for module, cls, method in PHASES:
        owner = getattr(importlib.import_module(module), cls)
        setattr(owner, method, timed(getattr(owner, method), f"{cls}.{method}", "phases"))
    TaskRunner.make = timed(TaskRunner.make, "", "make", named=lambda a: a[0].cue)  # type: ignore[method-assign]
    run = TaskRunner.run

    def timed_run(self, task_id):  # noqa: ANN001, ANN202
        c0 = time.process_time()
        try:
            return run(self, task_id)
        finally:
            rec["runs"].append([c0, time.process_time()])
            (folder / f"{os.getpid()}.json").write_text(json.dumps(rec))

    TaskRunner.run = timed_run  # type: ignore[method-assign]


def summary(folder: Path) -> dict:
    """Per view (views after the worker's first; one worker), ms: each cue's make, each phase, the whole run
    of a view's message and the worker's CPU between two views' runs."""
    (path,) = folder.glob("*.json")
    rec = json.loads(path.read_text())
    views = sorted({i for i, name, *_ in rec["phases"] if name == "TaskRunner.render_view"})[1:]
    n, steady = len(views), set(views)

    def per_view(table: str) -> dict:
        out: dict[str, list[float]] = {}
        for i, name, cpu, wall in rec[table]:
            if i in steady:
                total = out.setdefault(name, [0.0, 0.0])
                total[0] += cpu
                total[1] += wall
        return {k: {"cpu_ms": round(1000 * c / n, 2), "wall_ms": round(1000 * w / n, 2)}
                for k, (c, w) in sorted(out.items(), key=lambda kv: -kv[1][0])}

    runs = rec["runs"]
    between = [runs[b][0] - runs[a][1] for a, b in zip(views, views[1:], strict=False)]
    return {
        "views": n, "make": per_view("make"), "phases": per_view("phases"),
        "run_cpu_ms": round(1000 * statistics.median(runs[i][1] - runs[i][0] for i in views), 2),
        "between_views_cpu_ms": round(1000 * statistics.median(between), 2),
    }


def time_workers() -> None:
    """Each local worker of this process's `generate` times itself (install) before it serves tasks."""
    from services.embedded import pool

    work = pool._work

    def timed_work(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        install(Path(os.environ[ENV]))
        return work(*args, **kwargs)

    pool._work = timed_work


# python -c ENTRY THIS_FILE generate ARGS: loaded by path, so REV's checkout (PYTHONPATH) gives the services
ENTRY = ("import importlib.util, sys;"
         " spec = importlib.util.spec_from_file_location('worker_phases', sys.argv[1]);"
         " m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m); m.time_workers();"
         " from services.cli.main import main; sys.exit(main(sys.argv[2:]))")
