"""compacted_duration: the run-time histogram of compacted tasks, by job, cue and bucket (for /metrics).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | Sequence[str] | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BigIntId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "compacted_duration",
        sa.Column("job_id", BigIntId, nullable=False),
        sa.Column("cue", sa.String(64), nullable=False),
        sa.Column("bucket", sa.SmallInteger(), nullable=False),
        sa.Column("n", sa.BigInteger(), server_default=sa.text("0"), nullable=False),
        sa.Column("sum_s", sa.Float(), server_default=sa.text("0"), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], name="fk_compacted_duration_job_id_job", ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("job_id", "cue", "bucket", name="pk_compacted_duration"),
    )


def downgrade() -> None:
    op.drop_table("compacted_duration")
