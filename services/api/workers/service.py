"""Workers: heartbeat ages and current tasks; another tenant's task is reported as busy, without details.

A worker's counts (tasks done, labels/s, per-cue labels) sum every tenant's work, so a tenant is never shown
them (they would tell how much others render, and which cues): null and {}. An operator sees them all, and
every worker's current task.
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.api.pagination import PageParams
from services.api.workers.schemas import CurrentTask, WorkerRead
from services.core.db.models import Job, Task, Worker, utcnow


def list_workers(
    session: Session,
    *,
    tenant: str | None,
    page: PageParams,
    stale_s: float,
    alive: bool | None = None,
    now: datetime | None = None,
) -> tuple[list[WorkerRead], int]:
    """Workers by most recent heartbeat, optionally only live (or only stale) ones.

    stale_s: heartbeat age past which a worker is not alive; the scheduler's reaper declares it dead (and
    requeues its task) at Settings.heartbeat_timeout_s, so callers pass that.
    tenant: the caller's tenant, or None for an operator (service-wide figures, every current task).
    """
    now = now or utcnow()
    cutoff = now - timedelta(seconds=stale_s)
    cond = []
    if alive is True:
        cond.append(Worker.last_heartbeat >= cutoff)
    elif alive is False:
        cond.append(Worker.last_heartbeat < cutoff)
    total = session.scalar(select(func.count()).select_from(Worker).where(*cond)) or 0
    workers = session.scalars(
        select(Worker).where(*cond).order_by(Worker.last_heartbeat.desc(), Worker.id)
        .limit(page.limit).offset(page.offset)
    ).all()
    task_ids = [w.current_task_id for w in workers if w.current_task_id is not None]
    own: dict[int, Task] = {}
    if task_ids:
        query = select(Task).where(Task.id.in_(task_ids))
        if tenant is not None:
            query = query.join(Job, Job.id == Task.job_id).where(Job.owner == tenant)
        rows = session.scalars(query).all()
        own = {t.id: t for t in rows}
    items = []
    for w in workers:
        t = own.get(w.current_task_id) if w.current_task_id is not None else None
        age = max(0.0, (now - w.last_heartbeat).total_seconds())
        items.append(
            WorkerRead(
                id=w.id,
                host=w.host,
                queues=list(w.queues or []),
                started_at=w.started_at,
                last_heartbeat=w.last_heartbeat,
                heartbeat_age_s=round(age, 3),
                alive=age < stale_s,
                busy=w.current_task_id is not None,
                current_task=None
                if t is None
                else CurrentTask(id=t.id, job_id=t.job_id, cue=t.cue, space_id=t.space_id,
                                 point=t.point_idx, view=t.view_idx),
                # every tenant's work: an operator's to see, not one tenant's
                tasks_done=int(w.tasks_done or 0) if tenant is None else None,
                labels_per_s=float(w.labels_per_s or 0.0) if tenant is None else None,
                labels=dict(w.labels or {}) if tenant is None else {},
            )
        )
    return items, int(total)
