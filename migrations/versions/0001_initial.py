"""Initial schema: spaces, jobs, plans (cameras, points, views), tasks, counters, workers.

Revision ID: 0001
Revises:
Create Date: 2025-11-22
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0001"
down_revision: str | Sequence[str] | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the model types: a migration must not change when models.py does.
ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
DOC = sa.JSON(none_as_null=True).with_variant(postgresql.JSONB(none_as_null=True), "postgresql")
TS = sa.DateTime(timezone=True)
JOB_STATES = ("pending", "planning", "running", "paused", "done", "failed", "cancelled")
TASK_STATES = ("pending", "queued", "running", "done", "failed", "cancelled")


def _in(states: tuple[str, ...]) -> str:
    return "state IN (" + ", ".join(f"'{s}'" for s in states) + ")"


def _job_fk(table: str) -> sa.Column:
    fk = sa.ForeignKey("job.id", ondelete="CASCADE", name=f"fk_{table}_job_id_job")
    return sa.Column("job_id", ID, fk, nullable=False)


def _created(name: str = "created_at") -> sa.Column:
    return sa.Column(name, TS, server_default=sa.func.now(), nullable=False)


def upgrade() -> None:
    op.create_table(
        "space",
        sa.Column("id", ID, autoincrement=True, nullable=False),
        sa.Column("owner", sa.String(128), nullable=False),
        sa.Column("name", sa.String(128), nullable=False),
        sa.Column("source_key", sa.String(1024), nullable=False),
        sa.Column("source_format", sa.String(32), nullable=False),
        sa.Column("checksum", sa.String(64), nullable=False),
        sa.Column("unit_scale", sa.Float(), server_default=sa.text("1.0"), nullable=False),
        sa.Column("up_axis", sa.String(8), server_default="+z", nullable=False),
        sa.Column("source_to_world", DOC, nullable=True),
        sa.Column("bounds", DOC, nullable=True),
        sa.Column("face_count", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("vertex_count", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("has_texture", sa.Boolean(), server_default=sa.false(), nullable=False),
        sa.Column("has_semantics", sa.Boolean(), server_default=sa.false(), nullable=False),
        sa.Column("validation", DOC, nullable=True),
        _created(),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_space")),
        sa.UniqueConstraint("owner", "name", name=op.f("uq_space_owner_name")),
    )
    op.create_index(op.f("ix_space_owner"), "space", ["owner"])

    op.create_table(
        "job",
        sa.Column("id", ID, autoincrement=True, nullable=False),
        sa.Column("owner", sa.String(128), nullable=False),
        sa.Column("name", sa.String(128), nullable=False),
        sa.Column("spec", DOC, nullable=False),
        sa.Column("state", sa.String(16), server_default="pending", nullable=False),
        sa.Column("priority", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("output_root", sa.String(1024), server_default="", nullable=False),
        _created(),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("total_tasks", sa.BigInteger(), server_default=sa.text("0"), nullable=False),
        sa.Column("planner", sa.String(255), nullable=True),
        sa.Column("planner_lease_until", TS, nullable=True),
        sa.Column("plan_summary", DOC, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_job")),
        sa.CheckConstraint(_in(JOB_STATES), name=op.f("ck_job_state")),
    )
    op.create_index(op.f("ix_job_owner"), "job", ["owner"])
    op.create_index(op.f("ix_job_state"), "job", ["state"])

    op.create_table(
        "job_space",
        _job_fk("job_space"),
        sa.Column(
            "space_id", ID, sa.ForeignKey("space.id", ondelete="RESTRICT", name="fk_job_space_space_id_space"),
            nullable=False,
        ),
        sa.Column("position", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("cues", DOC, nullable=False),
        sa.PrimaryKeyConstraint("job_id", "space_id", name=op.f("pk_job_space")),
    )
    op.create_index(op.f("ix_job_space_space_id"), "job_space", ["space_id"])

    op.create_table(
        "job_counter",
        _job_fk("job_counter"),
        sa.Column("cue", sa.String(64), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("n", sa.BigInteger(), server_default=sa.text("0"), nullable=False),
        sa.PrimaryKeyConstraint("job_id", "cue", "state", name=op.f("pk_job_counter")),
    )

    op.create_table(
        "camera",
        _job_fk("camera"),
        sa.Column("space_id", ID, nullable=False),
        sa.Column("idx", sa.Integer(), nullable=False),
        sa.Column("x", sa.Float(), nullable=False),
        sa.Column("y", sa.Float(), nullable=False),
        sa.Column("z", sa.Float(), nullable=False),
        sa.Column("yaw", sa.Float(), server_default=sa.text("0"), nullable=False),
        sa.Column("roll", sa.Float(), server_default=sa.text("0"), nullable=False),
        sa.Column("source", sa.String(16), server_default="generated", nullable=False),
        sa.Column("uuid", sa.String(36), nullable=False),
        sa.PrimaryKeyConstraint("job_id", "space_id", "idx", name=op.f("pk_camera")),
    )

    op.create_table(
        "point",
        _job_fk("point"),
        sa.Column("space_id", ID, nullable=False),
        sa.Column("idx", sa.Integer(), nullable=False),
        sa.Column("x", sa.Float(), nullable=False),
        sa.Column("y", sa.Float(), nullable=False),
        sa.Column("z", sa.Float(), nullable=False),
        sa.Column("nx", sa.Float(), nullable=False),
        sa.Column("ny", sa.Float(), nullable=False),
        sa.Column("nz", sa.Float(), nullable=False),
        sa.Column("n_views", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("uuid", sa.String(36), nullable=False),
        sa.PrimaryKeyConstraint("job_id", "space_id", "idx", name=op.f("pk_point")),
    )

    op.create_table(
        "view",
        _job_fk("view"),
        sa.Column("space_id", ID, nullable=False),
        sa.Column("point_idx", sa.Integer(), nullable=False),
        sa.Column("v", sa.Integer(), nullable=False),
        sa.Column("camera_idx", sa.Integer(), nullable=False),
        sa.Column("fov", sa.Float(), nullable=False),
        sa.Column("roll", sa.Float(), server_default=sa.text("0"), nullable=False),
        sa.Column("resolution", sa.Integer(), nullable=False),
        sa.Column("obliqueness", sa.Float(), server_default=sa.text("0"), nullable=False),
        sa.Column("world_to_camera", DOC, nullable=False),
        sa.Column("in_sight", sa.Boolean(), server_default=sa.true(), nullable=False),
        sa.PrimaryKeyConstraint("job_id", "space_id", "point_idx", "v", name=op.f("pk_view")),
    )

    op.create_table(
        "task",
        sa.Column("id", ID, autoincrement=True, nullable=False),
        _job_fk("task"),
        sa.Column("space_id", ID, nullable=False),
        sa.Column("point_idx", sa.Integer(), nullable=False),
        sa.Column("view_idx", sa.Integer(), nullable=False),
        sa.Column("cue", sa.String(64), nullable=False),
        sa.Column("state", sa.String(16), server_default="pending", nullable=False),
        sa.Column("attempts", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("lease_until", TS, nullable=True),
        sa.Column("worker_id", sa.String(255), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("output_key", sa.String(1024), nullable=True),
        sa.Column("size", sa.BigInteger(), nullable=True),
        sa.Column("sha256", sa.String(64), nullable=True),
        sa.Column("duration_s", sa.Float(), nullable=True),
        sa.Column("queued_at", TS, nullable=True),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("not_before", TS, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_task")),
        sa.UniqueConstraint(
            "job_id", "space_id", "point_idx", "view_idx", "cue",
            name=op.f("uq_task_job_id_space_id_point_idx_view_idx_cue"),
        ),
        sa.CheckConstraint(_in(TASK_STATES), name=op.f("ck_task_state")),
    )
    op.create_index("ix_task_job_id_state", "task", ["job_id", "state"])
    op.create_index("ix_task_state_lease_until", "task", ["state", "lease_until"])

    op.create_table(
        "worker",
        sa.Column("id", sa.String(255), nullable=False),
        sa.Column("host", sa.String(255), nullable=False),
        sa.Column("queues", DOC, nullable=False),
        _created("started_at"),
        _created("last_heartbeat"),
        sa.Column("current_task_id", sa.BigInteger(), nullable=True),
        sa.Column("tasks_done", sa.BigInteger(), server_default=sa.text("0"), nullable=False),
        sa.Column("labels_per_s", sa.Float(), server_default=sa.text("0"), nullable=False),
        sa.Column("labels", DOC, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_worker")),
    )
    op.create_index(op.f("ix_worker_last_heartbeat"), "worker", ["last_heartbeat"])

    op.create_table(
        "worker_block",
        sa.Column("worker_id", sa.String(255), nullable=False),
        _job_fk("worker_block"),
        sa.Column("failures", sa.Integer(), server_default=sa.text("0"), nullable=False),
        sa.Column("until", TS, nullable=True),
        sa.PrimaryKeyConstraint("worker_id", "job_id", name=op.f("pk_worker_block")),
    )


def downgrade() -> None:
    for table in ("worker_block", "worker", "task", "view", "point", "camera", "job_counter", "job_space", "job",
                  "space"):
        op.drop_table(table)
