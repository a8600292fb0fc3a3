"""Dispatch index on pending tasks only: task (job_id, cue, id) WHERE state = 'pending', replacing 0002's
(job_id, state, cue, id) over every task.

Every state change of a task (dispatch, claim, result) is a non-HOT update that adds an entry to each of the
task table's indexes; 0002's index was the widest (~103 bytes per row of an 18M-task job) and only the dispatcher's
"pending tasks of one cue, oldest first" reads it. Partial, it holds the pending tasks alone: a task leaving
pending no longer writes into it, and a finished job's rows take no room in it. The dispatcher writes the
predicate's literal into its query so that the planner can use the index under a generic (prepared) plan too.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | Sequence[str] | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

PENDING = sa.text("state = 'pending'")


def upgrade() -> None:
    op.drop_index("ix_task_job_id_state_cue_id", table_name="task")
    op.create_index("ix_task_pending_job_id_cue_id", "task", ["job_id", "cue", "id"],
                    postgresql_where=PENDING, sqlite_where=PENDING)


def downgrade() -> None:
    op.drop_index("ix_task_pending_job_id_cue_id", table_name="task")
    op.create_index("ix_task_job_id_state_cue_id", "task", ["job_id", "state", "cue", "id"])
