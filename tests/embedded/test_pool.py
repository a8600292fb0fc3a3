"""Local worker processes started held: they import while `generate` validates and plans, and touch nothing
(no state, no --out) until released; a held pool stopped (a refused input) leaves nothing behind."""

from __future__ import annotations

import os
import time

from services.core.settings import get_settings
from services.embedded.job import worker_pool


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
