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
NEW, OLD = "ix_task_pending_job_id_cue_id", "ix_task_job_id_state_cue_id"


def _swap(create: tuple[str, list[str], sa.TextClause | None], drop: str) -> None:
    """Create one index, then drop the other. On Postgres both CONCURRENTLY, outside the migration's
    transaction: writes to a big task table go on meanwhile, and dispatch has an index throughout."""
    name, columns, where = create
    if op.get_bind().dialect.name != "postgresql":
        op.drop_index(drop, table_name="task")
        op.create_index(name, "task", columns, sqlite_where=where)
        return
    with op.get_context().autocommit_block():
        op.create_index(name, "task", columns, postgresql_where=where, postgresql_concurrently=True)
        op.drop_index(drop, table_name="task", postgresql_concurrently=True)


def upgrade() -> None:
    _swap((NEW, ["job_id", "cue", "id"], PENDING), OLD)


def downgrade() -> None:
    _swap((OLD, ["job_id", "state", "cue", "id"], None), NEW)
