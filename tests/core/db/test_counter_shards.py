"""Sharded progress counters and a worker's fixed-SQL moves (worker_moves.claim_task / finish_task), on a real
Postgres with concurrent connections: the counts stay exact while writers spread over shards. On Postgres and
on SQLite (the embedded default's own statements): a claim still refuses a paused job, a blocked worker and a
task that is not queued; a view batch's claim and result (claim_view_tasks / finish_tasks) move exactly the
rows they should, and the counters stay equal to the task rows."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session

from services.core.db.bulk import bulk_insert
from services.core.db.counters import add_counts, job_progress
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.models import Job, JobCounter, Task, WorkerBlock, utcnow
from services.core.db.states import transition
from services.core.db.worker_moves import claim_task, claim_view_tasks, finish_task, finish_tasks, task_state
from services.worker.tasks import worker_engine

CUES = ["rgb", "normal", "depth_zbuffer"]


def _migrated(url: str) -> Iterator[Engine]:
    migrate(url)
    eng = make_engine(url)
    yield eng
    eng.dispose()


@pytest.fixture()
def engine(empty_pg_url: str) -> Iterator[Engine]:
    yield from _migrated(empty_pg_url)


@pytest.fixture(params=["postgres", "sqlite"])
def any_engine(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Engine]:
    """Postgres (one statement a move) and SQLite (an UPDATE ... RETURNING and the counter upserts)."""
    url = (
        request.getfixturevalue("empty_pg_url")
        if request.param == "postgres"
        else f"sqlite:///{tmp_path / 'm.db'}"
    )
    yield from _migrated(url)


def _queued_job(session: Session, n_views: int) -> int:
    job = Job(owner="t", name="j", spec={}, state="running")
    session.add(job)
    session.flush()
    rows = {"job_id": [], "space_id": [], "point_idx": [], "view_idx": [], "cue": [], "state": []}
    for v in range(n_views):
        for cue in CUES:
            for k, val in (
                ("job_id", job.id), ("space_id", 1), ("point_idx", v), ("view_idx", 0), ("cue", cue),
                ("state", "queued"),
            ):
                rows[k].append(val)
    bulk_insert(session, Task, rows)
    add_counts(session, job.id, {(cue, "queued"): n_views for cue in CUES})
    session.commit()
    return int(job.id)


def _truth(session: Session, job_id: int) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for cue, state, n in session.execute(
        select(Task.cue, Task.state, func.count()).where(Task.job_id == job_id).group_by(Task.cue, Task.state)
    ):
        out.setdefault(cue, {})[state] = int(n)
    return out


def test_concurrent_workers_keep_counters_exact_across_shards(engine: Engine) -> None:
    sm = make_sessionmaker(engine)
    with sm() as s:
        job_id = _queued_job(s, 200)
        ids = list(s.scalars(select(Task.id).where(Task.job_id == job_id).order_by(Task.id)))
    wsm = make_sessionmaker(worker_engine(engine.url.render_as_string(hide_password=False), pool_size=8))
    claimed: list[int] = []
    lock = threading.Lock()

    def worker(k: int) -> None:
        for tid in ids:  # every worker tries every task: each is claimed exactly once
            now = utcnow()
            with wsm() as s:
                row = claim_task(
                    s, task_id=tid, worker_id=f"w{k}", now=now, lease_until=now + timedelta(seconds=60)
                )
            if row is None:
                continue
            with lock:
                claimed.append(tid)
            if tid % 2 == 0:  # half finish, half stay running
                with wsm() as s:
                    assert finish_task(s, task_id=tid, worker_id=f"w{k}", key=f"k{tid}", size=1,
                                       sha256="0" * 64, duration_s=0.01, now=utcnow())

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(claimed) == ids
    with sm() as s:
        truth = _truth(s, job_id)
        assert job_progress(s, job_id) == truth
        assert truth["rgb"] == {"running": 100, "done": 100}
        shards = s.scalar(
            select(func.count(func.distinct(JobCounter.shard))).where(JobCounter.job_id == job_id)
        )
        assert shards is not None and shards > 1  # eight connections wrote to more than one shard
        # a finish by a worker that does not hold the task moves nothing
        running = s.scalar(select(Task).where(Task.job_id == job_id, Task.state == "running").limit(1))
        assert running is not None
        assert not finish_task(s, task_id=running.id, worker_id="someone-else", key="x", size=1,
                               sha256="0" * 64, duration_s=0.0, now=utcnow())
        # and a transition through the generic path lands in the same sums
        transition(s, job_id=job_id, from_state="running", to_state="pending", task_ids=[running.id])
        s.commit()
        assert job_progress(s, job_id) == _truth(s, job_id)


def test_claim_refuses_paused_jobs_blocked_workers_and_tasks_not_queued(any_engine: Engine) -> None:
    sm = make_sessionmaker(any_engine)
    with sm() as s:
        job_id = _queued_job(s, 3)
        a, b, c = list(
            s.scalars(select(Task.id).where(Task.job_id == job_id, Task.cue == "rgb").order_by(Task.id))
        )
        now = utcnow()
        lease = now + timedelta(seconds=60)
        s.add(WorkerBlock(worker_id="bad", job_id=job_id, failures=3, until=now + timedelta(minutes=10)))
        s.commit()
    with sm() as s:
        # blocked on this job
        assert claim_task(s, task_id=a, worker_id="bad", now=now, lease_until=lease) is None
    with sm() as s:
        row = claim_task(s, task_id=a, worker_id="good", now=now, lease_until=lease)
        assert row is not None and (row.id, row.cue, row.job_id, row.attempts) == (a, "rgb", job_id, 1)
    # the times read back through the ORM as written (SQLite: the same text SQLAlchemy stores)
    with sm() as s:
        claimed = s.get(Task, a)
        assert claimed is not None and (claimed.started_at, claimed.lease_until) == (now, lease)
        assert s.scalar(select(func.count()).where(Task.id == a, Task.lease_until > now)) == 1
        # not queued any more
        assert claim_task(s, task_id=a, worker_id="other", now=now, lease_until=lease) is None
        job = s.get(Job, job_id)
        assert job is not None
        job.state = "paused"
        s.commit()
    with sm() as s:
        # job not running
        assert claim_task(s, task_id=b, worker_id="good", now=now, lease_until=lease) is None
        assert s.get(Task, c) is not None
        assert job_progress(s, job_id) == _truth(s, job_id)


def test_view_batch_claim_and_result_move_only_their_rows_and_keep_counters_exact(any_engine: Engine) -> None:
    sm = make_sessionmaker(any_engine)
    with sm() as s:
        job_id = _queued_job(s, 2)
        ids = {(int(p), str(c)): int(i) for i, p, c in s.execute(
            select(Task.id, Task.point_idx, Task.cue).where(Task.job_id == job_id))}
        now = utcnow()
        lease = now + timedelta(seconds=60)
        s.add(WorkerBlock(worker_id="bad", job_id=job_id, failures=3, until=now + timedelta(minutes=10)))
        s.commit()
    first = ids[(0, "rgb")]
    view = {"task_id": first, "job_id": job_id, "space_id": 1, "point": 0, "view": 0, "now": now,
            "lease_until": lease}
    with sm() as s:
        assert claim_view_tasks(s, worker_id="bad", **view) == []  # blocked on this job
        assert claim_task(s, task_id=first, worker_id="w", now=now, lease_until=lease) is not None
        rows = claim_view_tasks(s, worker_id="w", **view)
        # the view's other tasks only: not the claimed one, not the other point's
        assert sorted((int(r[0]), str(r[1]), int(r[3])) for r in rows) == sorted(
            (ids[(0, c)], c, 1) for c in ("normal", "depth_zbuffer"))
        assert claim_view_tasks(s, worker_id="w", **view) == []  # nothing queued left in the view
        assert task_state(s, first) == "running" and task_state(s, ids[(1, "rgb")]) == "queued"
        assert task_state(s, 10**12) is None
        mine = [ids[(0, c)] for c in CUES]
        results = [
            (tid, f"k{tid}", 10 + k, None if k == 1 else f"{k:064x}", 0.5 * k) for k, tid in enumerate(mine)
        ]
        not_mine = (ids[(1, "rgb")], "stray", 1, None, 0.0)  # queued, not held by "w": left alone
        assert finish_tasks(s, worker_id="other", results=results, now=now) == set()
        assert finish_tasks(s, worker_id="w", results=[*results, not_mine], now=now) == set(mine)
        got = {int(r.id): (r.state, r.output_key, r.size, r.sha256, r.duration_s)
               for r in s.execute(select(Task).where(Task.job_id == job_id)).scalars()}
        for tid, key, size, sha, dur in results:
            assert got[tid] == ("done", key, size, sha, dur)
        assert got[not_mine[0]][:2] == ("queued", None)
        assert job_progress(s, job_id) == _truth(s, job_id)
