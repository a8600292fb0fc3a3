"""bulk_insert (COPY on Postgres, executemany on SQLite) and the counters moved by transition()."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.db.bulk import bulk_insert
from services.core.db.counters import add_counts, init_counts, job_progress
from services.core.db.models import Job, JobCounter, Task, View, Worker
from services.core.db.states import transition

CUES = ("rgb", "normal", "depth_zbuffer", "edge_texture")


@pytest.fixture(params=["postgresql", "sqlite"])
def session(request: pytest.FixtureRequest) -> Session:
    """The same test on both dialects."""
    s: Session = request.getfixturevalue("db_session" if request.param == "postgresql" else "sqlite_session")
    return s


def _job(session: Session) -> Job:
    job = Job(owner="t", name="j", spec={})
    session.add(job)
    session.flush()
    return job


def _task_columns(job_id: int, n: int) -> dict[str, object]:
    """n tasks as numpy columns: 4 cues per view, 10 views per point."""
    i = np.arange(n)
    return {
        "job_id": np.full(n, job_id),
        "space_id": np.full(n, 7),
        "point_idx": i // (10 * len(CUES)),
        "view_idx": (i // len(CUES)) % 10,
        "cue": [CUES[k % len(CUES)] for k in range(n)],
    }


def _check_bulk(session: Session, n: int) -> None:
    job = _job(session)
    assert bulk_insert(session, Task, _task_columns(job.id, n)) == n
    count = session.scalar(select(func.count()).select_from(Task).where(Task.job_id == job.id))
    assert count == n
    k = n - 3  # a sample row near the end: server defaults filled, id assigned, columns in the right place
    row = session.scalars(
        select(Task).where(Task.job_id == job.id, Task.point_idx == k // 40, Task.view_idx == (k // 4) % 10,
                           Task.cue == CUES[k % 4])
    ).one()
    assert row.space_id == 7 and row.state == "pending" and row.attempts == 0 and row.id > 0
    assert row.lease_until is None and row.error is None


def test_bulk_insert_200k_tasks_postgres(db_session: Session) -> None:
    _check_bulk(db_session, 200_000)


def test_bulk_insert_20k_tasks_sqlite(sqlite_session: Session) -> None:
    _check_bulk(sqlite_session, 20_000)
    sqlite_session.commit()


def test_bulk_insert_types_and_escaping(session: Session) -> None:
    job = _job(session)
    when = datetime(2025, 5, 6, 7, 8, 9, 123456, tzinfo=UTC)
    nasty = "tab\there\nnewline back\\slash \\N 'quote' \"dq\" ünïcode"
    rows = [
        {"job_id": job.id, "space_id": 1, "point_idx": 0, "view_idx": v, "cue": "rgb", "error": err,
         "not_before": nb, "size": 2**40 + v, "duration_s": 0.25}
        for v, err, nb in [(0, nasty, when), (1, None, None), (2, "", datetime(2025, 1, 1, 12, 0))]
    ]
    assert bulk_insert(session, Task.__table__, rows) == 3
    got = {t.view_idx: t for t in session.scalars(select(Task).where(Task.job_id == job.id))}
    assert got[0].error == nasty and got[0].not_before == when and got[0].size == 2**40
    assert got[1].error is None and got[1].not_before is None
    assert got[2].error == ""
    assert got[2].not_before == datetime(2025, 1, 1, 12, 0, tzinfo=UTC)  # naive means UTC
    views = {
        "job_id": [job.id] * 2, "space_id": [1, 1], "point_idx": [0, 0], "v": [0, 1], "camera_idx": [3, 4],
        "fov": [1.2, 1.3], "resolution": [512, 512], "world_to_camera": [list(np.eye(4).ravel()), [0.5] * 16],
        "in_sight": [True, False],
    }
    assert bulk_insert(session, View, views) == 2
    v = {x.v: x for x in session.scalars(select(View).where(View.job_id == job.id))}
    assert v[0].world_to_camera == list(np.eye(4).ravel()) and v[1].world_to_camera == [0.5] * 16
    assert v[0].in_sight is True and v[1].in_sight is False and v[1].roll == 0.0
    bulk_insert(
        session, Worker, [{"id": "h:1", "host": "h", "queues": ["render", "derive"], "labels": {"rgb": 3}}]
    )
    w = session.get(Worker, "h:1")
    assert w is not None and w.queues == ["render", "derive"] and w.labels == {"rgb": 3}


def test_bulk_insert_refuses_bad_input(session: Session) -> None:
    assert bulk_insert(session, Task, []) == 0
    assert bulk_insert(session, Task, {"job_id": []}) == 0
    with pytest.raises(ValueError, match="different lengths"):
        bulk_insert(session, Task, {"job_id": [1, 2], "cue": ["rgb"]})
    with pytest.raises(ValueError, match="no column"):
        bulk_insert(session, Task, [{"job_id": 1, "colour": "red"}])
    with pytest.raises(ValueError, match="row 1 has keys"):
        bulk_insert(session, Task, [{"job_id": 1, "cue": "a"}, {"job_id": 1}])


def test_counters_follow_transitions(session: Session) -> None:
    job = _job(session)
    other = _job(session)
    bulk_insert(session, Task, _task_columns(job.id, 40))  # 10 tasks per cue
    bulk_insert(session, Task, _task_columns(other.id, 8))
    init_counts(session, job.id, {c: 10 for c in CUES})
    init_counts(session, other.id, {c: 2 for c in CUES})
    assert job_progress(session, job.id) == {c: {"pending": 10} for c in CUES}

    ids = {
        c: list(
            session.scalars(select(Task.id).where(Task.job_id == job.id, Task.cue == c).order_by(Task.id))
        )
        for c in CUES
    }
    lease = datetime.now(UTC) + timedelta(minutes=5)
    moved = transition(session, job_id=job.id, task_ids=ids["rgb"][:6] + ids["normal"][:2],
                       from_state="pending", to_state="queued", queued_at=datetime.now(UTC))
    assert sorted(c for _, c in moved) == ["normal"] * 2 + ["rgb"] * 6
    assert job_progress(session, job.id)["rgb"] == {"pending": 4, "queued": 6}
    assert job_progress(session, job.id)["normal"] == {"pending": 8, "queued": 2}

    # repeating the same transition moves nothing (tasks are no longer pending): racing dispatchers are safe
    assert (
        transition(session, job_id=job.id, task_ids=ids["rgb"][:6], from_state="pending", to_state="queued")
        == []
    )
    # another job's ids are never touched through this job
    other_ids = list(session.scalars(select(Task.id).where(Task.job_id == other.id)))
    assert (
        transition(session, job_id=job.id, task_ids=other_ids, from_state="pending", to_state="queued") == []
    )

    moved = transition(
        session, job_id=job.id, task_ids=ids["rgb"][:3], from_state="queued", to_state="running",
        worker_id="host:9", lease_until=lease, attempts=Task.attempts + 1,
    )
    assert {i for i, _ in moved} == set(ids["rgb"][:3])
    t = session.get(Task, ids["rgb"][0], populate_existing=True)
    assert t is not None and (t.state, t.worker_id, t.attempts) == ("running", "host:9", 1)
    assert t.lease_until == lease
    transition(session, job_id=job.id, task_ids=ids["rgb"][:2], from_state="running", to_state="done")
    transition(session, job_id=job.id, task_ids=ids["rgb"][2:3], from_state="running", to_state="failed",
               error="boom")
    session.commit()

    progress = job_progress(session, job.id)
    assert progress["rgb"] == {"pending": 4, "queued": 3, "done": 2, "failed": 1}
    assert progress["depth_zbuffer"] == {"pending": 10}
    # the counters agree with the truth in the task table
    truth = dict(session.execute(
        select(Task.state, func.count()).where(Task.job_id == job.id, Task.cue == "rgb").group_by(Task.state)
    ).all())
    assert truth == progress["rgb"]
    assert job_progress(session, other.id) == {c: {"pending": 2} for c in CUES}
    with pytest.raises(ValueError):
        transition(session, job_id=job.id, task_ids=[1], from_state="done", to_state="done")


def test_add_counts_upserts(session: Session) -> None:
    job = _job(session)
    add_counts(session, job.id, {("rgb", "done"): 5, ("rgb", "failed"): 0})
    add_counts(session, job.id, {("rgb", "done"): 2, ("normal", "done"): 1})
    add_counts(session, job.id, {})
    assert job_progress(session, job.id) == {"normal": {"done": 1}, "rgb": {"done": 7}}
    rows = session.scalar(select(func.count()).select_from(JobCounter).where(JobCounter.job_id == job.id))
    assert rows == 2  # zero deltas create no rows


def test_transition_in_chunks(sqlite_session: Session) -> None:
    # more ids than one UPDATE takes: several statements, one counter update
    job = _job(sqlite_session)
    bulk_insert(sqlite_session, Task, _task_columns(job.id, 12_000))
    init_counts(sqlite_session, job.id, {c: 3_000 for c in CUES})
    ids = list(sqlite_session.scalars(select(Task.id).where(Task.job_id == job.id)))
    moved = transition(
        sqlite_session, job_id=job.id, task_ids=ids, from_state="pending", to_state="cancelled"
    )
    assert len(moved) == 12_000
    assert job_progress(sqlite_session, job.id) == {c: {"cancelled": 3_000} for c in CUES}
