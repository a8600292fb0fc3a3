"""Database rows: SQLAlchemy 2.0 typed models, one module, for Postgres and SQLite.

Units: positions in metres in the space's world frame (+Z up), angles in radians, times timezone-aware UTC.
Job progress lives in `job_counter` rows maintained incrementally (services.core.db.counters), never
COUNT(*) on tasks.
"""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    SmallInteger,
    String,
    Text,
    UniqueConstraint,
    false,
    func,
    text,
    true,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

from services.core.domain.json_types import (
    JSONValue,  # dict[str, JSONValue], not the JSONObject alias: SQLAlchemy evaluates it
)


class JobState(StrEnum):
    """A job's lifecycle state (the allowed changes: services/core/db/states.py)."""

    PENDING = "pending"
    PLANNING = "planning"
    RUNNING = "running"
    PAUSED = "paused"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


class TaskState(StrEnum):
    """A task's state (the allowed changes: services/core/db/states.py)."""

    PENDING = "pending"
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


JOB_STATES: tuple[str, ...] = tuple(JobState)
JOB_TERMINAL_STATES: tuple[str, ...] = (JobState.DONE, JobState.FAILED, JobState.CANCELLED)
TASK_STATES: tuple[str, ...] = tuple(TaskState)
TASK_TERMINAL_STATES: tuple[str, ...] = (TaskState.DONE, TaskState.FAILED, TaskState.CANCELLED)
TASK_ACTIVE_STATES: tuple[str, ...] = (TaskState.PENDING, TaskState.QUEUED, TaskState.RUNNING)

# Constraint names are deterministic so Alembic migrations can refer to them on both dialects.
NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

# Autoincrement ids: BIGSERIAL on Postgres; SQLite only autoincrements an INTEGER PRIMARY KEY.
BigIntId = BigInteger().with_variant(Integer(), "sqlite")
# JSON documents: JSONB on Postgres (indexable, compact), JSON text on SQLite; Python None is SQL NULL.
JSONDoc = JSON(none_as_null=True).with_variant(JSONB(none_as_null=True), "postgresql")


def utcnow() -> datetime:
    """Current time, timezone-aware UTC."""
    return datetime.now(UTC)


class StateColumn(TypeDecorator[str]):
    """A state column: VARCHAR(16) in the database, the state enum in Python (JobState or TaskState).

    Rows read back carry the enum, so `job.state` has the type its annotation says. Writes pass the text
    through unchecked: the table's CHECK constraint is the one judge of a valid state.
    """

    impl = String(16)
    cache_ok = True

    def __init__(self, states: type[StrEnum]) -> None:
        super().__init__()
        self.states = states

    def process_bind_param(self, value: str | None, dialect: Dialect) -> str | None:
        return None if value is None else str(value)

    def process_result_value(self, value: str | None, dialect: Dialect) -> StrEnum | None:
        return None if value is None else self.states(value)


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on both dialects (SQLite stores naive UTC text, we re-attach UTC)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        value = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def _state_check(states: tuple[str, ...]) -> str:
    return "state IN (" + ", ".join(f"'{s}'" for s in states) + ")"


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


def _created_at() -> Mapped[datetime]:
    return mapped_column(UTCDateTime(), default=utcnow, server_default=func.now(), nullable=False)


class Space(Base):
    """An uploaded scan: where its source lives, how to bring it to the world frame, and what it has."""

    __tablename__ = "space"
    __table_args__ = (UniqueConstraint("owner", "name"),)

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True, autoincrement=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    name: Mapped[str] = mapped_column(String(128))
    source_key: Mapped[str] = mapped_column(
        String(1024), doc="object-store key or URI of the source file/zip"
    )
    source_format: Mapped[str] = mapped_column(String(32))
    checksum: Mapped[str] = mapped_column(String(64), doc="sha256 hex of the uploaded bytes")
    unit_scale: Mapped[float] = mapped_column(Float, default=1.0, server_default=text("1.0"))
    up_axis: Mapped[str] = mapped_column(String(8), default="+z", server_default="+z")
    source_to_world: Mapped[list[list[float]] | None] = mapped_column(
        JSONDoc, doc="4x4 row-major, source -> world"
    )
    bounds: Mapped[list[list[float]] | None] = mapped_column(
        JSONDoc, doc="[[minx,miny,minz],[maxx,maxy,maxz]] metres"
    )
    face_count: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    vertex_count: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    has_texture: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    has_semantics: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    validation: Mapped[dict[str, Any] | None] = mapped_column(JSONDoc)
    created_at: Mapped[datetime] = _created_at()


class Job(Base):
    """A generation job: its JobSpec, lifecycle state and the planner that owns its planning step."""

    __tablename__ = "job"
    __table_args__ = (CheckConstraint(_state_check(JOB_STATES), name="state"),)

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True, autoincrement=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    name: Mapped[str] = mapped_column(String(128))
    spec: Mapped[dict[str, JSONValue]] = mapped_column(JSONDoc, doc='JobSpec.model_dump(mode="json")')
    state: Mapped[JobState] = mapped_column(StateColumn(JobState), default=JobState.PENDING,
                                            server_default="pending", index=True)
    priority: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    error: Mapped[str | None] = mapped_column(Text)
    output_root: Mapped[str] = mapped_column(String(1024), default="", server_default="")
    created_at: Mapped[datetime] = _created_at()
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    total_tasks: Mapped[int] = mapped_column(BigInteger, default=0, server_default=text("0"))
    planner: Mapped[str | None] = mapped_column(String(255), doc="id of the scheduler process planning it")
    planner_lease_until: Mapped[datetime | None] = mapped_column(
        UTCDateTime(), doc="another planner may take the job over after this"
    )
    plan_summary: Mapped[dict[str, Any] | None] = mapped_column(JSONDoc)
    paused_by: Mapped[str | None] = mapped_column(
        String(16), doc="'storage': paused by the service while its store fails "
        "(services.core.db.jobs.hold_for_storage); NULL: paused by its owner, or not paused")


class JobSpace(Base):
    """A space of a job, in submission order, with the cue list resolved for it."""

    __tablename__ = "job_space"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    space_id: Mapped[int] = mapped_column(
        BigIntId, ForeignKey("space.id", ondelete="RESTRICT"), primary_key=True, index=True
    )
    position: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    cues: Mapped[list[str]] = mapped_column(JSONDoc, default=list)


class JobCounter(Base):
    """A share of the number of a job's tasks of one cue in one state, updated in the transaction that moves
    the tasks. Writers spread over `shard`s (so a fleet of workers does not queue on one row's lock); the
    count is the sum over the shards."""

    __tablename__ = "job_counter"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    cue: Mapped[str] = mapped_column(String(64), primary_key=True)
    state: Mapped[TaskState] = mapped_column(StateColumn(TaskState), primary_key=True)
    # n before shard: the migrated table's column order (0003 added shard last), which create_all then gives
    # too
    n: Mapped[int] = mapped_column(BigInteger, default=0, server_default=text("0"))
    shard: Mapped[int] = mapped_column(SmallInteger, primary_key=True, default=0, server_default=text("0"))


class Camera(Base):
    """A camera of a job's plan for one space: centre (metres, world) and yaw/roll (radians)."""

    __tablename__ = "camera"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    space_id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    z: Mapped[float] = mapped_column(Float)
    yaw: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    roll: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    source: Mapped[str] = mapped_column(String(16), default="generated", server_default="generated")
    uuid: Mapped[str] = mapped_column(String(36))


class Point(Base):
    """A point of interest on the surface (metres, world) with its unit normal and number of views."""

    __tablename__ = "point"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    space_id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    z: Mapped[float] = mapped_column(Float)
    nx: Mapped[float] = mapped_column(Float)
    ny: Mapped[float] = mapped_column(Float)
    nz: Mapped[float] = mapped_column(Float)
    n_views: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    uuid: Mapped[str] = mapped_column(String(36))


class View(Base):
    """View v of a point: the camera it is taken from, fov/roll/obliqueness (radians) and its pose."""

    __tablename__ = "view"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    space_id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    point_idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    v: Mapped[int] = mapped_column(Integer, primary_key=True)
    camera_idx: Mapped[int] = mapped_column(Integer)
    fov: Mapped[float] = mapped_column(Float)
    roll: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    resolution: Mapped[int] = mapped_column(Integer)
    obliqueness: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    world_to_camera: Mapped[list[float]] = mapped_column(
        JSONDoc, doc="16 floats, row-major, OpenCV camera axes"
    )
    in_sight: Mapped[bool] = mapped_column(Boolean, default=True, server_default=true())


class Task(Base):
    """One point-view-cue unit of work; Postgres is the source of truth for its state (Redis
    only carries its id, so a lost message loses nothing)."""

    __tablename__ = "task"
    __table_args__ = (
        UniqueConstraint("job_id", "space_id", "point_idx", "view_idx", "cue"),
        Index("ix_task_job_id_state", "job_id", "state"),
        # dispatch: the pending tasks of a cue, oldest first; partial, so leaving pending writes nothing here
        # (0004)
        Index("ix_task_pending_job_id_cue_id", "job_id", "cue", "id",
              postgresql_where=text("state = 'pending'"), sqlite_where=text("state = 'pending'")),
        Index("ix_task_state_lease_until", "state", "lease_until"),
        CheckConstraint(_state_check(TASK_STATES), name="state"),
    )

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True, autoincrement=True)
    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"))
    space_id: Mapped[int] = mapped_column(BigIntId)
    point_idx: Mapped[int] = mapped_column(Integer)
    view_idx: Mapped[int] = mapped_column(Integer)
    cue: Mapped[str] = mapped_column(String(64))
    state: Mapped[TaskState] = mapped_column(StateColumn(TaskState), default=TaskState.PENDING,
                                             server_default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    lease_until: Mapped[datetime | None] = mapped_column(UTCDateTime())
    worker_id: Mapped[str | None] = mapped_column(String(255))
    error: Mapped[str | None] = mapped_column(Text)
    output_key: Mapped[str | None] = mapped_column(String(1024))
    size: Mapped[int | None] = mapped_column(BigInteger)
    sha256: Mapped[str | None] = mapped_column(String(64))
    duration_s: Mapped[float | None] = mapped_column(Float)
    queued_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    not_before: Mapped[datetime | None] = mapped_column(
        UTCDateTime(), doc="retry backoff: not dispatched before"
    )


class ViewOutput(Base):
    """The finished tasks of one view, compacted into one row (services.scheduler.compaction): what the
    manifest, the views API and a resume need of them, packed by services.core.db.view_outputs (per task: id,
    cue, attempts, size, sha256, duration, finish time, and the output key only where it is not the
    deterministic one). `cue_mask` has bit i set for the catalog's i-th cue among them."""

    __tablename__ = "view_output"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    space_id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    point_idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    view_idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    cue_mask: Mapped[int] = mapped_column(BigInteger)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), doc="the last of its tasks to finish")
    outputs: Mapped[bytes] = mapped_column(LargeBinary)


class CompactedDuration(Base):
    """Run times of a job's compacted tasks of one cue in one histogram bucket
    (services.core.db.durations)."""

    __tablename__ = "compacted_duration"

    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    cue: Mapped[str] = mapped_column(String(64), primary_key=True)
    bucket: Mapped[int] = mapped_column(SmallInteger, primary_key=True)
    n: Mapped[int] = mapped_column(BigInteger, default=0, server_default=text("0"))
    sum_s: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))


class Worker(Base):
    """A worker process (id host:pid) and its heartbeat; labels maps cue -> labels produced."""

    __tablename__ = "worker"

    id: Mapped[str] = mapped_column(String(255), primary_key=True)
    host: Mapped[str] = mapped_column(String(255))
    queues: Mapped[list[str]] = mapped_column(JSONDoc, default=list)
    started_at: Mapped[datetime] = _created_at()
    last_heartbeat: Mapped[datetime] = mapped_column(
        UTCDateTime(), default=utcnow, server_default=func.now(), index=True
    )
    current_task_id: Mapped[int | None] = mapped_column(BigInteger)
    tasks_done: Mapped[int] = mapped_column(BigInteger, default=0, server_default=text("0"))
    labels_per_s: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    labels: Mapped[dict[str, int]] = mapped_column(JSONDoc, default=dict)


class WorkerBlock(Base):
    """A worker kept off a job after repeated failures there (until a time, or for good when None)."""

    __tablename__ = "worker_block"

    worker_id: Mapped[str] = mapped_column(String(255), primary_key=True)
    job_id: Mapped[int] = mapped_column(BigIntId, ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    failures: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    until: Mapped[datetime | None] = mapped_column(UTCDateTime())
