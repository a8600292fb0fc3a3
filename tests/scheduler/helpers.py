"""Builders and fixtures shared by the scheduler-service tests: synthetic plans (no mesh), spaces, running
jobs, fake workers, and session factories on Postgres (rolled back) and SQLite.

Test modules import the fixtures they use from here (`from tests.scheduler.helpers import any_sm, ...`).
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import numpy as np
import pytest
from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session, sessionmaker

from services.core.camera import look_at
from services.core.db import job_progress, make_engine, make_sessionmaker
from services.core.jobs import create_job, job_spaces
from services.core.jobspec import JobSpec
from services.core.models import Job, Space, Task, utcnow
from services.core.plan import CameraPose, PlannedView, PointOfInterest, SpacePlan
from services.core.states import transition
from services.core.storage import ObjectStore
from services.scheduler.compile import compile_tasks
from services.scheduler.persist import persist_space
from tests.conftest import rolled_back


def synthetic_plan(space_name: str, n_points: int, views_per_point: int, resolution: int = 64,
                   seed: int = 0) -> SpacePlan:
    """A plan of `n_points` points with `views_per_point` views each, cameras on a circle (no mesh needed)."""
    rng = np.random.default_rng(seed)
    n_cams = max(views_per_point, 4)
    ang = np.linspace(0, 2 * np.pi, n_cams, endpoint=False)
    cams = tuple(
        CameraPose(i, np.array([5 * np.cos(a), 5 * np.sin(a), 1.5]), "generated", str(uuid.UUID(int=i + 1)))
        for i, a in enumerate(ang)
    )
    pts_xyz = rng.uniform(-1, 1, size=(n_points, 3))
    points = tuple(
        PointOfInterest(p, pts_xyz[p], np.array([0.0, 0.0, 1.0]), str(uuid.UUID(int=10**6 + p)),
                        tuple(range(views_per_point)))
        for p in range(n_points)
    )
    views = tuple(
        PlannedView(p, v, v, look_at(cams[v].position, pts_xyz[p]), np.deg2rad(70.0), 0.0, resolution, 0.3, True)
        for p in range(n_points)
        for v in range(views_per_point)
    )
    return SpacePlan(space_name, cams, points, views)


def make_space(session: Session, *, owner: str = "alice", name: str | None = None,
               has_semantics: bool = False) -> Space:
    """A space row whose source is never read (the tests plan synthetically)."""
    sp = Space(
        owner=owner, name=name or f"space-{uuid.uuid4().hex[:8]}", source_key="spaces/none/none.ply",
        source_format="ply", checksum="0" * 64, has_semantics=has_semantics,
        source_to_world=np.eye(4).tolist(), bounds=[[-1, -1, -1], [1, 1, 1]],
    )
    session.add(sp)
    session.flush()
    return sp


def make_running_job(
    session: Session, store: ObjectStore, *, cues: list[str] | None, n_points: int = 2, views: int = 2,
    priority: int = 0, owner: str = "alice", spaces: list[Space] | None = None, name: str = "omnidata",
    output_root: str | None = None, max_attempts: int = 3,
) -> Job:
    """A job planned from synthetic plans and set running (committed)."""
    spaces = spaces or [make_space(session, owner=owner)]
    spec = JobSpec(name=name, cues=cues, priority=priority, max_attempts=max_attempts)
    job = create_job(session, owner=owner, spec=spec, spaces=spaces, output_root=output_root)
    total = 0
    for js, sp in job_spaces(session, job.id):
        plan = synthetic_plan(sp.name, n_points, views, seed=js.position)
        tasks = compile_tasks(plan, js.cues, sp.id)
        total += persist_space(session, store, job, sp.id, plan, tasks).tasks
    job.state = "running"
    job.total_tasks = total
    session.commit()
    return job


def claim(session: Session, job_id: int, ids: list[int], worker: str = "w1", lease_s: float = 60) -> list[int]:
    """What a worker does on receipt: queued -> running with a lease (not committed)."""
    moved = transition(
        session, job_id=job_id, task_ids=ids, from_state="queued", to_state="running",
        worker_id=worker, attempts=Task.attempts + 1, started_at=utcnow(),
        lease_until=utcnow() + timedelta(seconds=lease_s),
    )
    return [i for i, _ in moved]


def complete(session: Session, job: Job, ids: list[int]) -> list[int]:
    """running -> done with recorded outputs, as a worker would (outputs not written), then commit."""
    rows = session.execute(
        select(Task.id, Task.cue, Task.point_idx, Task.view_idx).where(Task.id.in_(ids), Task.state == "running")
    ).all()
    for tid, cue, p, v in rows:
        transition(
            session, job_id=job.id, task_ids=[tid], from_state="running", to_state="done",
            output_key=f"{job.output_root}/{cue}/x/p{p}v{v}", size=10 + tid, sha256=f"{tid:064x}",
            finished_at=utcnow(), lease_until=None,
        )
    session.commit()
    return [int(r[0]) for r in rows]


def finish(session: Session, job: Job, ids: list[int], worker: str = "w1") -> list[int]:
    """Claim and complete queued tasks as a worker would, then commit."""
    return complete(session, job, claim(session, job.id, ids, worker))


def task_counts(session: Session, job_id: int) -> dict[str, dict[str, int]]:
    """{cue: {state: n}} by COUNT(*) (the ground truth the counters must equal)."""
    out: dict[str, dict[str, int]] = {}
    for cue, state, n in session.execute(
        select(Task.cue, Task.state, func.count()).where(Task.job_id == job_id).group_by(Task.cue, Task.state)
    ):
        out.setdefault(cue, {})[state] = int(n)
    return out


def assert_counters_exact(session: Session, job_id: int) -> None:
    """The incremental counters equal COUNT(*) by cue and state."""
    assert job_progress(session, job_id) == task_counts(session, job_id)


def states(session: Session, ids: list[int]) -> dict[int, str]:
    """Task id -> state."""
    return {int(i): str(s) for i, s in session.execute(select(Task.id, Task.state).where(Task.id.in_(ids)))}


def task_ids(session: Session, job_id: int, **where: Any) -> list[int]:
    """Ids of the job's tasks matching column equality filters, in id order."""
    q = select(Task.id).where(Task.job_id == job_id)
    for k, v in where.items():
        q = q.where(getattr(Task, k) == v)
    return [int(r[0]) for r in session.execute(q.order_by(Task.id))]


@pytest.fixture()
def pg_sm(pg_engine: Engine) -> Iterator[sessionmaker[Session]]:
    """Sessions on one Postgres connection inside a transaction rolled back after the test.

    Commits inside the code under test become savepoints; rows other tests committed are truncated first,
    so each test starts from an empty database.
    """
    with rolled_back(pg_engine) as conn:
        yield sessionmaker(bind=conn, join_transaction_mode="create_savepoint", expire_on_commit=False)


@pytest.fixture()
def sqlite_sm(sqlite_url: str) -> Iterator[sessionmaker[Session]]:
    """Sessions on a fresh migrated SQLite file (the embedded database)."""
    engine = make_engine(sqlite_url)
    try:
        yield make_sessionmaker(engine)
    finally:
        engine.dispose()


@pytest.fixture(params=["postgres", "sqlite"])
def any_sm(request: pytest.FixtureRequest) -> sessionmaker[Session]:
    """The same test on Postgres and on SQLite."""
    return request.getfixturevalue("pg_sm" if request.param == "postgres" else "sqlite_sm")
