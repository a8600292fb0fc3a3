"""Counter shards: job_counter gets a `shard` column in its primary key (job_id, cue, state, shard).

Every claim and result of a job's whole fleet moved the same (job, cue, state) counter rows, so concurrent
workers queued on those rows' locks (pg_stat_activity: Lock:transactionid, bench/scale_sim.py). A transaction
now adds its deltas to the rows of one shard (on Postgres: its backend pid modulo COUNTER_SHARDS), and readers
sum the shards: still a bounded handful of rows per job (cues x states x shards), never a COUNT(*) of tasks.
Existing rows become shard 0.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | Sequence[str] | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("job_counter") as batch:
        batch.add_column(sa.Column("shard", sa.SmallInteger(), server_default=sa.text("0"), nullable=False))
        batch.drop_constraint("pk_job_counter", type_="primary")
        batch.create_primary_key("pk_job_counter", ["job_id", "cue", "state", "shard"])


def downgrade() -> None:
    # fold the shards back into one row per (job, cue, state) before the column goes
    op.execute(
        "UPDATE job_counter SET n = (SELECT sum(s.n) FROM job_counter s WHERE s.job_id = job_counter.job_id "
        "AND s.cue = job_counter.cue AND s.state = job_counter.state) WHERE shard = (SELECT min(m.shard) "
        "FROM job_counter m WHERE m.job_id = job_counter.job_id AND m.cue = job_counter.cue "
        "AND m.state = job_counter.state)"
    )
    op.execute(
        "DELETE FROM job_counter WHERE shard <> (SELECT min(m.shard) FROM job_counter m WHERE "
        "m.job_id = job_counter.job_id AND m.cue = job_counter.cue AND m.state = job_counter.state)"
    )
    with op.batch_alter_table("job_counter") as batch:
        batch.drop_constraint("pk_job_counter", type_="primary")
        batch.create_primary_key("pk_job_counter", ["job_id", "cue", "state"])
        batch.drop_column("shard")
