"""Local worker processes started held: they import while `generate` validates and plans, and touch nothing
(no state, no --out) until released; a held pool stopped (a refused input) leaves nothing behind."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from services.core.settings import get_settings
from services.embedded.job import worker_pool

ROOT = Path(__file__).resolve().parents[2]


def _wait_alive(pool, seconds: float = 30.0) -> None:
    deadline = time.monotonic() + seconds
    while not all(p.is_alive() for p in pool.procs) and time.monotonic() < deadline:
        time.sleep(0.05)


def test_held_workers_touch_nothing_and_stop_when_the_run_is_refused(tmp_path):
    out = tmp_path / "out"  # does not exist: a worker past its hold would create it (its object store)
    settings = get_settings(database_url=f"sqlite:///{tmp_path / 'absent' / 'state.db'}")
    pool = worker_pool(out, settings, 2)
    pool.start(held=True)
    _wait_alive(pool)
    time.sleep(5.0)  # long enough for the imports (Blender's included) to finish and the workers to wait
    assert all(p.is_alive() for p in pool.procs)
    assert not out.exists() and not (tmp_path / "absent").exists()
    assert pool.drain(0.1) == []  # no worker reported ready: none is past its hold
    pids = [p.pid for p in pool.procs]
    pool.stop()
    assert pool.procs == []
    for pid in pids:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            continue
        raise AssertionError(f"worker {pid} still runs after the held pool stopped")
    assert not out.exists()


def test_a_worker_spawned_by_a_process_that_imported_blender_still_imports_it():
    # A spawned child inherits its parent's sys.path, Blender's script folders included once the parent imported
    # bpy (as the test process has, or a service embedding generate): their pure-Python `bpy` package came first
    # and the worker failed with "No module named '_bpy'".
    import bpy  # noqa: F401  (puts Blender's script folders on this process's sys.path)

    probe = ("import sys\n"
             f"sys.path[:0] = {[p for p in sys.path if 'scripts' in p and 'bpy' in p]!r}\n"
             "from services.worker.blender.threads import import_bpy\n"
             "import_bpy(1)\n"
             "import bpy\n"
             "print(bpy.app.version_string)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip()
