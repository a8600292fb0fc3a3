"""job.paused_by: why the service paused a job ('storage': its object store failed; it resumes on its own once
the store takes writes again). NULL for a job its owner paused, or one not paused.

Revision ID: 0007 Revises: 0006 Create Date: 2026-12-06
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | Sequence[str] | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    column = sa.Column("paused_by", sa.String(16), nullable=True)
    if op.get_bind().dialect.name == "sqlite":
        # rebuilt, not ALTER TABLE ADD COLUMN, with the defaults as the models write them (reflected, they
        # come back in parentheses): its schema text is then the one the models create
        defaults = [sa.Column("output_root", sa.String(1024), server_default="", nullable=False),
                    sa.Column("created_at", sa.DateTime(), server_default=sa.func.now(), nullable=False)]
        # The rebuild drops the old table: with foreign keys enforced, that would cascade to every job's rows.
        op.execute("PRAGMA foreign_keys=OFF")
        with op.batch_alter_table("job", recreate="always", reflect_args=defaults) as batch:
            batch.add_column(column)
        op.execute("PRAGMA foreign_keys=ON")
    else:
        op.add_column("job", column)


def downgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.drop_column("paused_by")
