"""Models on Postgres and SQLite: round trips, UTC times, JSON NULLs, constraints, cascades, naming."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.core.db.models import (
    JOB_STATES,
    TASK_STATES,
    Base,
    Camera,
    Job,
    JobSpace,
    Point,
    Space,
    Task,
    View,
    Worker,
    WorkerBlock,
)
from services.core.domain.jobspec import JobSpec


@pytest.fixture(params=["postgresql", "sqlite"])
def session(request: pytest.FixtureRequest) -> Session:
    """The same test on both dialects."""
    s: Session = request.getfixturevalue("db_session" if request.param == "postgresql" else "sqlite_session")
    return s


def _space(owner: str = "tenant-a", name: str = "bunny") -> Space:
    return Space(
        owner=owner, name=name, source_key="spaces/1/bun.ply", source_format="ply", checksum="0" * 64,
        source_to_world=[[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]],
        bounds=[[-0.1, -0.1, 0.0], [0.1, 0.1, 0.15]], face_count=69451, vertex_count=35947,
    )


def _job(owner: str = "tenant-a") -> Job:
    return Job(owner=owner, name="omnidata", spec=JobSpec().model_dump(mode="json"), output_root="jobs/1")


def test_state_constants() -> None:
    assert TASK_STATES == ("pending", "queued", "running", "done", "failed", "cancelled")
    assert set(JOB_STATES) == {"pending", "planning", "running", "paused", "done", "failed", "cancelled"}


def test_full_plan_round_trip(session: Session) -> None:
    space, job = _space(), _job()
    session.add_all([space, job])
    session.flush()
    when = datetime(2025, 1, 2, 3, 4, 5, 678901, tzinfo=timezone(timedelta(hours=2)))
    session.add_all(
        [
            JobSpace(job_id=job.id, space_id=space.id, position=0, cues=["rgb", "normal"]),
            Camera(
                job_id=job.id, space_id=space.id, idx=0, x=1.0, y=2.0, z=1.5, yaw=0.5, roll=-0.1, uuid="c0"
            ),
            Point(
                job_id=job.id, space_id=space.id, idx=0, x=0, y=0, z=0.1, nx=0, ny=0, nz=1, n_views=3,
                uuid="p0",
            ),
            View(
                job_id=job.id, space_id=space.id, point_idx=0, v=0, camera_idx=0, fov=1.35, resolution=512,
                world_to_camera=[float(i) for i in range(16)],
            ),
            Task(job_id=job.id, space_id=space.id, point_idx=0, view_idx=0, cue="rgb", not_before=when),
            Worker(id="host:1", host="host", queues=["render"]),
            WorkerBlock(worker_id="host:1", job_id=job.id, failures=2),
        ]
    )
    session.commit()
    session.expunge_all()

    job2 = session.get(Job, job.id)
    assert job2 is not None
    assert job2.state == "pending" and job2.total_tasks == 0 and job2.priority == 0
    assert JobSpec.model_validate(job2.spec) == JobSpec()
    assert job2.created_at.tzinfo is not None and job2.created_at.utcoffset() == timedelta(0)
    assert abs(job2.created_at - datetime.now(UTC)) < timedelta(minutes=5)
    sp = session.get(Space, space.id)
    assert sp is not None and sp.bounds == [[-0.1, -0.1, 0.0], [0.1, 0.1, 0.15]]
    assert sp.unit_scale == 1.0 and sp.up_axis == "+z" and sp.has_texture is False
    assert sp.validation is None
    # None in a JSON column is SQL NULL, not the JSON literal null
    assert session.scalar(select(func.count()).select_from(Space).where(Space.validation.is_(None))) == 1
    task = session.scalars(select(Task).where(Task.job_id == job.id)).one()
    assert task.state == "pending" and task.attempts == 0 and task.lease_until is None
    assert task.not_before == when and task.not_before.tzinfo == UTC  # stored as UTC, same instant
    view = session.get(View, (job.id, space.id, 0, 0))
    assert view is not None and view.in_sight is True and view.world_to_camera[15] == 15.0
    assert session.get(Camera, (job.id, space.id, 0)).source == "generated"  # type: ignore[union-attr]
    w = session.get(Worker, "host:1")
    assert w is not None and w.queues == ["render"] and w.labels == {} and w.tasks_done == 0
    assert w.last_heartbeat.tzinfo is not None


def test_unique_space_name_per_owner(session: Session) -> None:
    session.add_all([_space("a", "room"), _space("b", "room")])  # same name, other tenant: fine
    session.commit()
    session.add(_space("a", "room"))
    with pytest.raises(IntegrityError):
        session.flush()
    session.rollback()


def test_task_identity_is_unique(session: Session) -> None:
    job = _job()
    session.add(job)
    session.flush()
    session.add(Task(job_id=job.id, space_id=1, point_idx=0, view_idx=0, cue="rgb"))
    session.commit()
    session.add(Task(job_id=job.id, space_id=1, point_idx=0, view_idx=0, cue="rgb"))
    with pytest.raises(IntegrityError):
        session.flush()
    session.rollback()


def test_states_are_checked(session: Session) -> None:
    job = _job()
    session.add(job)
    session.commit()
    session.add(Task(job_id=job.id, space_id=1, point_idx=0, view_idx=0, cue="rgb", state="exploded"))
    with pytest.raises(IntegrityError):
        session.flush()
    session.rollback()
    job.state = "sleeping"
    with pytest.raises(IntegrityError):
        session.flush()
    session.rollback()


def test_deleting_a_job_cascades(session: Session) -> None:
    job = _job()
    session.add(job)
    session.flush()
    session.add_all([
        Task(job_id=job.id, space_id=1, point_idx=p, view_idx=0, cue="rgb") for p in range(3)
    ] + [Camera(job_id=job.id, space_id=1, idx=0, x=0, y=0, z=0, uuid="c")])
    session.commit()
    session.execute(delete(Job).where(Job.id == job.id))
    session.commit()
    assert session.scalar(select(func.count()).select_from(Task)) == 0
    assert session.scalar(select(func.count()).select_from(Camera)) == 0


def test_tasks_need_an_existing_job(session: Session) -> None:
    session.add(Task(job_id=987654, space_id=1, point_idx=0, view_idx=0, cue="rgb"))
    with pytest.raises(IntegrityError):
        session.flush()
    session.rollback()


def test_constraint_names_follow_the_convention() -> None:
    task = Base.metadata.tables["task"]
    names = {c.name for c in task.constraints} | {i.name for i in task.indexes}
    assert {"pk_task", "uq_task_job_id_space_id_point_idx_view_idx_cue", "ck_task_state",
            "fk_task_job_id_job", "ix_task_job_id_state", "ix_task_state_lease_until"} <= names
    assert {i.name for i in Base.metadata.tables["job"].indexes} == {"ix_job_owner", "ix_job_state"}
