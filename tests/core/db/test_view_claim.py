"""A whole-view batch claim (worker_moves.claim_view_tasks with_pending=True, issue 20/23): after its render,
the rest of a view moves from pending AND queued to running, on a real Postgres (one fixed statement whose
counter deltas subtract each row's own old state) and on SQLite (an UPDATE per source state, then the
counters). The counter shards must still sum to the task rows; the claim must respect a paused job, a blocked
worker, a failed task of the view and rows of other views; concurrent claims of the same view take each task
once."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.bulk import bulk_insert
from services.core.db.counters import add_counts, job_progress
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.models import Job, Task, WorkerBlock, utcnow
from services.core.db.states import TASK_EDGES, TaskState, transition
from services.core.db.worker_moves import claim_view_tasks
from services.worker.tasks import worker_engine

# one view: passes (running, ours) and its cues in the states a real view has after its render
VIEW = {"passes": "running", "rgb": "pending", "normal": "pending", "depth_zbuffer": "queued",
        "mask_valid": "pending", "point_info": "queued", "vanishing_points": "done"}


def _migrated(url: str) -> Iterator[Engine]:
    migrate(url)
    eng = make_engine(url)
    yield eng
    eng.dispose()


@pytest.fixture(params=["postgres", "sqlite"])
def engine(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Engine]:
    url = (
        request.getfixturevalue("empty_pg_url")
        if request.param == "postgres"
        else f"sqlite:///{tmp_path / 'v.db'}"
    )
    yield from _migrated(url)


@pytest.fixture
def pg_engine_empty(empty_pg_url: str) -> Iterator[Engine]:
    """Postgres only: concurrent claimers need a database with more than one writer (SQLite has one)."""
    yield from _migrated(empty_pg_url)


def _job(s: Session, n_points: int) -> int:
    job = Job(owner="t", name="j", spec={}, state="running")
    s.add(job)
    s.flush()
    cols: dict[str, list[object]] = {
        k: [] for k in ("job_id", "space_id", "point_idx", "view_idx", "cue", "state")
    }
    deltas: dict[tuple[str, str], int] = {}
    for p in range(n_points):
        for cue, state in VIEW.items():
            for k, v in zip(cols, (job.id, 1, p, 0, cue, state), strict=True):
                cols[k].append(v)
            deltas[(cue, state)] = deltas.get((cue, state), 0) + 1
    bulk_insert(s, Task, cols)
    add_counts(s, job.id, deltas)
    s.commit()
    return int(job.id)


def _truth(s: Session, job_id: int) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    rows = s.execute(select(Task.cue, Task.state, func.count()).where(Task.job_id == job_id)
                     .group_by(Task.cue, Task.state))
    for cue, state, n in rows:
        out.setdefault(cue, {})[state] = int(n)
    return out


def _ids(s: Session, job_id: int) -> dict[tuple[int, str], int]:
    return {(int(p), str(c)): int(i) for i, p, c in s.execute(
        select(Task.id, Task.point_idx, Task.cue).where(Task.job_id == job_id))}


def _claim(sm: sessionmaker[Session], ids: dict[tuple[int, str], int], job_id: int, point: int, worker: str,
           with_pending: bool = True) -> list[tuple[int, str, int, str]]:
    now = utcnow()
    with sm() as s:
        rows = claim_view_tasks(
            s, task_id=ids[(point, "passes")], job_id=job_id, space_id=1, point=point, view=0,
            worker_id=worker, now=now, lease_until=now + timedelta(seconds=60), with_pending=with_pending,
        )
    return sorted((int(r[0]), str(r[1]), int(r[3]), str(r[4])) for r in rows)


def test_the_edge_is_in_the_table() -> None:
    assert TaskState.RUNNING in TASK_EDGES[TaskState.PENDING]


def test_a_mixed_pending_and_queued_batch_moves_its_rows_and_keeps_the_counters_exact(engine: Engine) -> None:
    sm = make_sessionmaker(engine)
    with sm() as s:
        job_id = _job(s, 4)
        ids = _ids(s, job_id)
        s.add(WorkerBlock(worker_id="bad", job_id=job_id, failures=3, until=utcnow() + timedelta(minutes=10)))
        s.commit()
    assert _claim(sm, ids, job_id, 0, "bad") == []  # blocked on this job
    # the derived cue's batch: queued only
    assert _claim(sm, ids, job_id, 0, "w", with_pending=False) == sorted(
        (ids[(0, c)], c, 1, "queued") for c in ("depth_zbuffer", "point_info"))
    got = _claim(sm, ids, job_id, 1, "w")
    # every pending or queued task of point 1's view, each with its old state; not passes, not the done one
    assert got == sorted((ids[(1, c)], c, 1, st) for c, st in VIEW.items() if st in ("pending", "queued")
                         and c != "passes")
    assert _claim(sm, ids, job_id, 1, "w2") == []  # nothing left to take
    with sm() as s:
        assert job_progress(s, job_id) == _truth(s, job_id)
        rows = s.execute(select(Task.id, Task.state, Task.worker_id).where(Task.point_idx == 1)).all()
        assert {(st, w) for i, st, w in rows if i in {g[0] for g in got}} == {("running", "w")}
        # a failed task in a view: its pending tasks stay for the dispatcher (it fails what depends on it)
        transition(s, job_id=job_id, task_ids=[ids[(2, "normal")]], from_state="pending", to_state="queued")
        transition(s, job_id=job_id, task_ids=[ids[(2, "normal")]], from_state="queued", to_state="running")
        transition(s, job_id=job_id, task_ids=[ids[(2, "normal")]], from_state="running", to_state="failed")
        s.commit()
    assert [c for _, c, _, _ in _claim(sm, ids, job_id, 2, "w")] == sorted(["depth_zbuffer", "point_info"])
    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None
        job.state = "paused"
        s.commit()
    assert _claim(sm, ids, job_id, 3, "w") == []  # the job is not running
    with sm() as s:
        assert job_progress(s, job_id) == _truth(s, job_id)


def test_concurrent_batch_claims_of_one_view_take_each_task_once(pg_engine_empty: Engine) -> None:
    engine = pg_engine_empty
    sm = make_sessionmaker(engine)
    with sm() as s:
        job_id = _job(s, 30)
        ids = _ids(s, job_id)
    wsm = make_sessionmaker(worker_engine(engine.url.render_as_string(hide_password=False), pool_size=6))
    taken: list[int] = []
    lock = threading.Lock()

    def worker(k: int) -> None:
        for p in range(30):
            got = _claim(wsm, ids, job_id, p, f"w{k}")
            with lock:
                taken.extend(g[0] for g in got)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    want = sorted(i for (p, c), i in ids.items() if VIEW[c] in ("pending", "queued"))
    assert sorted(taken) == want  # each once
    with sm() as s:
        assert job_progress(s, job_id) == _truth(s, job_id)
