# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""The scheduler's care of the store: a job whose files cannot be written for a full store is held (paused,
saying why) and finished once space is back; temp files of writers killed mid-write are swept. SQLite only: a
held job on the shared Postgres database would fail other tests' /ready meanwhile."""

from __future__ import annotations

import os
import time
from pathlib import Path

from services.core.db.models import Job
from services.core.settings import get_settings
from services.core.storage import LocalStore
from services.scheduler.completion import complete_once
from services.scheduler.dispatch import dispatch_once
from services.scheduler.loop import Scheduler
from services.scheduler.store_watch import StoreWatch
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import finish, make_running_job, sqlite_sm  # noqa: F401  (fixtures)
from tests.fixtures.small_disk import fill, small_tmpfs


def test_a_job_whose_files_meet_a_full_store_is_held_then_finished(sqlite_sm, tmp_path: Path):
    with small_tmpfs(tmp_path / "disk", 16) as disk, sqlite_sm() as s:
        store = LocalStore(disk)
        job = make_running_job(s, store, cues=["rgb"], n_points=2, views=2, name="full")
        while True:  # every task done, level by level of the cue graph
            tr = NullTransport()
            dispatch_once(s, tr, window=1000)
            if not tr.sent:
                break
            finish(s, job, [i for i, _ in tr.sent])
        ballast = fill(disk)
        assert complete_once(s, store) == []
        s.refresh(job)
        assert (job.state, job.paused_by) == ("paused", "storage") and "storage full" in (job.error or "")

        watch = StoreWatch(sqlite_sm, store, interval_s=0.0)
        assert watch.check() == []
        ballast.unlink()
        assert watch.check() == [job.id]
        (fin,) = complete_once(s, store)
        assert (fin.job_id, fin.state, fin.error) == (job.id, "done", None)
        s.expire_all()
        assert s.get(Job, job.id).paused_by is None  # type: ignore[union-attr]
        assert store.exists(f"{job.output_root}/manifest.jsonl")


def test_the_reaper_pass_sweeps_stale_temp_files_and_keeps_writes_in_flight(sqlite_sm, tmp_path: Path):
    store = LocalStore(tmp_path / "objects")
    stale = store.root / "jobs" / "1" / "rgb" / ".a.png.tmp-0123456789abcdef0123456789abcdef"
    fresh = stale.with_name(".b.png.tmp-0123456789abcdef0123456789abcdef")
    stale.parent.mkdir(parents=True)
    for p in (stale, fresh):
        p.write_bytes(b"partial")
    hour_ago = time.time() - 3600
    os.utime(stale, (hour_ago, hour_ago))  # a worker killed an hour ago
    sched = Scheduler(sqlite_sm, store, NullTransport(), get_settings(data_dir=tmp_path), "s")
    sched.reap_once()
    assert sched.sweep is not None and sched.sweep.result(timeout=30) == 1
    assert not stale.exists() and fresh.exists()
