"""view_output: the done tasks of a finished view compacted into one row (services.scheduler.compaction).

A 1M-view x 18-cue job is 18M task rows at ~350 bytes each once done; the starter dataset's 14.6M views would hold
~94 GB of them. Compaction replaces a finished view's task rows by one row of this table (~1.2 KB packed), which
every reader of done tasks (manifest, views API, resume, deletion) reads too.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | Sequence[str] | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BigIntId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "view_output",
        sa.Column("job_id", BigIntId, nullable=False),
        sa.Column("space_id", BigIntId, nullable=False),
        sa.Column("point_idx", sa.Integer(), nullable=False),
        sa.Column("view_idx", sa.Integer(), nullable=False),
        sa.Column("cue_mask", sa.BigInteger(), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("outputs", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], name="fk_view_output_job_id_job", ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("job_id", "space_id", "point_idx", "view_idx", name="pk_view_output"),
    )


def downgrade() -> None:
    # a downgrade would lose the compacted outputs: refuse while there are any (expand them first: a resume)
    conn = op.get_bind()
    if conn.execute(sa.text("SELECT 1 FROM view_output LIMIT 1")).first() is not None:
        raise RuntimeError("view_output holds compacted views; downgrading would lose their outputs")
    op.drop_table("view_output")
