"""Reaper: give back tasks whose worker died (lease expired) or whose message was lost (queued too long).

- running, lease_until < now: the worker stopped heart-beating (kill -9, node lost). The attempt it
  made counts: with attempts < max_attempts the task goes back to pending after a backoff, else it
  fails for good with the reason kept. Tasks of a cancelled job are cancelled instead.
- queued, queued_at < now - queued_timeout: the message never reached a worker (Redis restarted
  without persistence); back to pending with attempts unchanged, to be sent again.
Rows are locked (FOR UPDATE SKIP LOCKED on Postgres) between the check and the move, so a worker
extending its lease or claiming the task at that moment either wins before us or sees the new state.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from services.core.jobs import retry_backoff_s
from services.core.models import Job, JobState, Task, TaskState, utcnow
from services.core.states import transition

log = logging.getLogger(__name__)

REAP_BATCH = 10_000  # rows looked at per kind per pass


@dataclass
class ReapResult:
    """Tasks moved by one reaper pass."""

    expired_retried: int = 0  # running -> pending (lease expired, attempts left)
    expired_failed: int = 0  # running -> failed (lease expired, no attempts left)
    expired_cancelled: int = 0  # running -> cancelled (job cancelled meanwhile)
    lost_requeued: int = 0  # queued -> pending (message lost)

    @property
    def total(self) -> int:
        """All tasks moved."""
        return self.expired_retried + self.expired_failed + self.expired_cancelled + self.lost_requeued


def _locked(session: Session, stmt: Any) -> Any:
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update(skip_locked=True, of=Task)
    return session.execute(stmt).all()


def reap_once(
    session: Session, *, queued_timeout_s: float, now: datetime | None = None, default_max_attempts: int = 3
) -> ReapResult:
    """One reaper pass over expired leases and lost queued tasks; commits. Returns the counts."""
    now = now or utcnow()
    res = ReapResult()

    expired = _locked(
        session,
        select(Task.id, Task.job_id, Task.attempts, Task.worker_id, Job.state, Job.spec)
        .join(Job, Job.id == Task.job_id)
        .where(Task.state == TaskState.RUNNING, Task.lease_until < now)
        .order_by(Task.id)
        .limit(REAP_BATCH),
    )
    by_job: dict[int, list[Any]] = defaultdict(list)
    for row in expired:
        by_job[int(row.job_id)].append(row)
    for job_id, rows in by_job.items():
        job_state, spec = rows[0].state, rows[0].spec or {}
        if job_state == JobState.CANCELLED:
            res.expired_cancelled += len(transition(
                session, job_id=job_id, task_ids=[r.id for r in rows], from_state=TaskState.RUNNING,
                to_state=TaskState.CANCELLED, finished_at=now, lease_until=None,
            ))
            continue
        max_attempts = int(spec.get("max_attempts") or default_max_attempts)
        retry: dict[float, list[int]] = defaultdict(list)
        fail: list[Any] = []
        for r in rows:
            if int(r.attempts) < max_attempts:
                retry[retry_backoff_s(int(r.attempts))].append(int(r.id))
            else:
                fail.append(r)
        for backoff, ids in retry.items():
            res.expired_retried += len(transition(
                session, job_id=job_id, task_ids=ids, from_state=TaskState.RUNNING, to_state=TaskState.PENDING,
                lease_until=None, worker_id=None, queued_at=None,
                not_before=now + timedelta(seconds=backoff),
                error="lease expired: the worker stopped heart-beating (lost or killed); retrying",
            ))
        for r in fail:  # one by one: each keeps its own error text (few: only tasks out of attempts)
            res.expired_failed += len(transition(
                session, job_id=job_id, task_ids=[r.id], from_state=TaskState.RUNNING, to_state=TaskState.FAILED,
                lease_until=None, finished_at=now,
                error=(
                    f"LeaseExpired: worker {r.worker_id} stopped heart-beating while running this task; "
                    f"gave up after {r.attempts} attempt(s) (max_attempts={max_attempts})"
                ),
            ))

    cutoff = now - timedelta(seconds=queued_timeout_s)
    lost = _locked(
        session,
        select(Task.id, Task.job_id)
        .where(Task.state == TaskState.QUEUED, Task.queued_at < cutoff)
        .order_by(Task.id)
        .limit(REAP_BATCH),
    )
    lost_by_job: dict[int, list[int]] = defaultdict(list)
    for row in lost:
        lost_by_job[int(row.job_id)].append(int(row.id))
    for job_id, ids in lost_by_job.items():
        res.lost_requeued += len(transition(
            session, job_id=job_id, task_ids=ids, from_state=TaskState.QUEUED, to_state=TaskState.PENDING, queued_at=None,
        ))
    session.commit()
    if res.total:
        log.info(
            "reaper: %d expired leases retried, %d failed, %d cancelled; %d lost queued tasks requeued",
            res.expired_retried, res.expired_failed, res.expired_cancelled, res.lost_requeued,
        )
    return res
