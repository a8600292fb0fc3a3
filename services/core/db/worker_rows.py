"""Expiry of worker rows: a worker silent for `Settings.worker_expiry_s` is gone, and its row leaves /workers.

Rows are keyed by the worker's name (`omnidata worker --hostname`), so a recycled child process keeps its row;
rows of workers that were stopped or lost for good would otherwise pile up. A row still named by a running
task is kept, so the reaper can report which worker held it.
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import delete, exists, select
from sqlalchemy.orm import Session

from services.core.db.models import Task, TaskState, Worker, utcnow


def expire_worker_rows(session: Session, *, older_than_s: float, now: datetime | None = None) -> int:
    """Delete the rows of workers without a heartbeat for `older_than_s` seconds; commits; returns how
    many."""
    cutoff = (now or utcnow()) - timedelta(seconds=older_than_s)
    holds_a_task = exists(select(Task.id).where(Task.worker_id == Worker.id, Task.state == TaskState.RUNNING))
    res = session.execute(
        delete(Worker)
        .where(Worker.last_heartbeat < cutoff, ~holds_a_task)
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return int(res.rowcount or 0)  # type: ignore[attr-defined]
