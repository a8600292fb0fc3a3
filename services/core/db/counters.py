"""The incremental progress counters: one `job_counter` row per (job, cue, state).

Task state changes adjust them in the same transaction (services.core.db.states), so progress is read
from a handful of rows instead of COUNT(*) over millions of tasks.
"""

from __future__ import annotations

from collections.abc import Mapping

from sqlalchemy import select
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from services.core.db.bulk import connection_of, insert_for_dialect, table_of
from services.core.db.models import JobCounter, TaskState


def add_counts(session: Session | Connection, job_id: int, deltas: Mapping[tuple[str, str], int]) -> None:
    """Add `deltas[(cue, state)]` to the job's counters (UPSERT: n = n + excluded.n); zero deltas are skipped."""
    items = sorted((k, d) for k, d in deltas.items() if d)  # fixed order: concurrent upserts lock rows alike
    if not items:
        return
    conn = connection_of(session)
    ins = insert_for_dialect(conn)(table_of(JobCounter)).values(
        [{"job_id": job_id, "cue": cue, "state": state, "n": d} for (cue, state), d in items]
    )
    stmt = ins.on_conflict_do_update(
        index_elements=["job_id", "cue", "state"], set_={"n": table_of(JobCounter).c.n + ins.excluded.n}
    )
    conn.execute(stmt)


def init_counts(session: Session | Connection, job_id: int, pending: Mapping[str, int]) -> None:
    """Record freshly planned tasks: `pending[cue]` tasks of each cue in state 'pending'."""
    add_counts(session, job_id, {(cue, TaskState.PENDING): n for cue, n in pending.items()})


def job_progress(session: Session | Connection, job_id: int) -> dict[str, dict[str, int]]:
    """Task counts of a job as {cue: {state: n}}, read from job_counter only (zero counts omitted)."""
    c = table_of(JobCounter).c
    out: dict[str, dict[str, int]] = {}
    rows = connection_of(session).execute(
        select(c.cue, c.state, c.n).where(c.job_id == job_id, c.n != 0).order_by(c.cue, c.state)
    )
    for cue, state, n in rows:
        out.setdefault(cue, {})[state] = int(n)
    return out
