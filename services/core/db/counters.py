"""The incremental progress counters: `job_counter` rows per (job, cue, state), sharded.

Task state changes adjust them in the same transaction (services.core.db.states; on Postgres in the same
statement), so progress is read from a handful of rows instead of COUNT(*) over millions of tasks. Writers
spread over COUNTER_SHARDS rows per (job, cue, state) so that a fleet of workers does not queue on one row's
lock; a count is the sum over its shards.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

from sqlalchemy import TextClause, func, select, text
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from services.core.db.bulk import connection_of, table_of
from services.core.db.models import JobCounter, TaskState

# Counter rows per (job, cue, state) that concurrent writers spread over (migration 0003): on Postgres a
# statement adds its deltas to shard (backend pid mod COUNTER_SHARDS), and as a connection runs one
# transaction at a time, two transactions share a row only when their pids collide. SQLite has one writer at a
# time anyway: shard 0.
COUNTER_SHARDS = 16


# SQL text built once per dialect: SQLAlchemy cannot cache the compiled form of its INSERT ... ON CONFLICT DO
# UPDATE construct, and compiling it anew on every state change cost more CPU than the database spent running
# it.
@functools.cache
def _add_counts_sql(dialect: str) -> TextClause:
    shard = f"mod(pg_backend_pid(), {COUNTER_SHARDS})" if dialect == "postgresql" else "0"
    return text(
        f"INSERT INTO job_counter (job_id, cue, state, shard, n) VALUES (:job_id, :cue, :state, {shard}, :n) "
        "ON CONFLICT (job_id, cue, state, shard) DO UPDATE SET n = job_counter.n + excluded.n"
    )


def add_counts(session: Session | Connection, job_id: int, deltas: Mapping[tuple[str, str], int]) -> None:
    """Add `deltas[(cue, state)]` to the job's counters (UPSERT into this connection's shard: n = n +
    excluded.n); zero deltas are skipped."""
    items = sorted((k, d) for k, d in deltas.items() if d)  # fixed order: concurrent upserts lock rows alike
    if not items:
        return
    conn = connection_of(session)
    conn.execute(_add_counts_sql(conn.dialect.name),
                 [{"job_id": job_id, "cue": cue, "state": state, "n": d} for (cue, state), d in items])


def init_counts(session: Session | Connection, job_id: int, pending: Mapping[str, int]) -> None:
    """Record freshly planned tasks: `pending[cue]` tasks of each cue in state 'pending'."""
    add_counts(session, job_id, {(cue, TaskState.PENDING): n for cue, n in pending.items()})


def summed_counters(job_ids: Any) -> Any:
    """SELECT job_id, cue, state, n: the counters of `job_ids` (a list, or a correlated column such as Job.id)
    summed over their shards, zero counts left out."""
    c = table_of(JobCounter).c
    listed = isinstance(job_ids, list | tuple)
    n = func.sum(c.n)
    stmt = (
        select(c.job_id, c.cue, c.state, n.label("n"))
        .where(c.job_id.in_(job_ids) if listed else c.job_id == job_ids)
        .group_by(c.job_id, c.cue, c.state)
        .having(n != 0)
    )
    return stmt if listed else stmt.correlate(job_ids.table)


def job_progress(session: Session | Connection, job_id: int) -> dict[str, dict[str, int]]:
    """Task counts of a job as {cue: {state: n}}, read from job_counter only (zero counts omitted)."""
    out: dict[str, dict[str, int]] = {}
    sub = summed_counters([job_id]).subquery()
    rows = connection_of(session).execute(
        select(sub.c.cue, sub.c.state, sub.c.n).order_by(sub.c.cue, sub.c.state)
    )
    for cue, state, n in rows:
        out.setdefault(cue, {})[state] = int(n)
    return out
