"""Dispatch index: task (job_id, state, cue, id), so 'pending tasks of one cue of a job, oldest first' is one
ordered index scan.

The dispatcher asks, per cue, for `... WHERE job_id = :j AND state = 'pending' AND cue = :c ORDER BY id LIMIT :n`
many times a second; with (job_id, state) alone Postgres would sort every pending task of a 1M-task job.

Revision ID: 0002
Revises: 0001
Create Date: 2025-11-22
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0002"
down_revision: str | Sequence[str] | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_index("ix_task_job_id_state_cue_id", "task", ["job_id", "state", "cue", "id"])


def downgrade() -> None:
    op.drop_index("ix_task_job_id_state_cue_id", table_name="task")
