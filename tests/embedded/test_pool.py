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
    # A spawned child inherits its parent's sys.path, Blender's script folders included once the parent
    # imported bpy (as the test process has, or a service embedding generate): their pure-Python `bpy` package
    # came first and the worker failed with "No module named '_bpy'".
    import bpy  # noqa: F401  (puts Blender's script folders on this process's sys.path)

    probe = ("import sys\n"
             f"sys.path[:0] = {[p for p in sys.path if 'scripts' in p and 'bpy' in p]!r}\n"
             "from services.worker.blender.threads import import_bpy\nimport_bpy(1)\nimport bpy\n"
             "print(bpy.app.version_string)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip()


HELD_STOP_PROBE = """
import sys, time
from pathlib import Path
from services.core.settings import get_settings
from services.embedded.job import worker_pool

tmp = Path(sys.argv[1])
pool = worker_pool(tmp / "out", get_settings(database_url=f"sqlite:///{tmp / 'state.db'}"), 1)
pool.start(held=True)
proc = pool.procs[0]
maps = Path(f"/proc/{proc.pid}/maps")
deadline = time.monotonic() + 60
while "bpy/__init__" not in maps.read_text() and time.monotonic() < deadline:  # Blender's library is loading
    time.sleep(0.002)
time.sleep(float(sys.argv[2]))
pool.stop()
print(proc.exitcode)
"""


def test_a_held_worker_stopped_while_it_loads_blender_exits_at_once_and_quietly(tmp_path):
    # A finished job resumed stops its held workers as they load Blender. SIGTERM used to raise SystemExit
    # inside Blender's start-up scripts, run from C: PyErr_Print then exited through Blender's C++
    # destructors, which printed their leak report on the user's terminal, or deadlocked until the pool's kill
    # 3 s later.
    for delay in (0.0, 0.05, 0.15, 0.3):
        run = subprocess.run(
            [sys.executable, "-c", HELD_STOP_PROBE, str(tmp_path), str(delay)], capture_output=True,
            text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        assert run.returncode == 0, run.stderr[-2000:]
        # not killed (-9)
        assert run.stdout.split()[-1] in ("0", "143"), (delay, run.stdout, run.stderr[-2000:])
        assert "leak detector" not in run.stderr and "Not freed memory" not in run.stderr, (
            delay, run.stderr[-2000:],
        )
    assert not (tmp_path / "out").exists()
