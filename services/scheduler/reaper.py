"""Reaper: give back tasks whose worker died (declared dead, or lease expired) or whose message was lost.

- running, and its worker declared dead: the worker's row has had no heartbeat for `dead_after_s`
  (kill -9, node lost; beats come every 5 s) or no row at all (each process beats once before its first
  claim, Heartbeat.start: one without a row was killed before that beat landed), and the task started before
  that too. This requeues a dead worker's task within about a minute instead of when its lease of minutes runs
  out.
- running, lease_until < now: the lease ran out (a worker whose beats stopped extending it).
  Either way the attempt it made counts: with attempts < max_attempts the task goes back to pending
  after a backoff, else it fails for good with the reason kept. Tasks of a cancelled job are cancelled
  instead.
- queued, queued_at < now - queued_timeout: the message never reached a worker (Redis restarted
  without persistence); back to pending with attempts unchanged, to be sent again.
Rows are locked (FOR UPDATE SKIP LOCKED on Postgres) between the check and the move, so a worker
extending its lease or claiming the task at that moment either wins before us or sees the new state.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import TypeVar

from sqlalchemy import Row, Select, and_, or_, select
from sqlalchemy.orm import Session

from services.core.db.jobs import retry_backoff_s
from services.core.db.models import Job, JobState, Task, TaskState, Worker, utcnow
from services.core.db.states import transition
from services.core.domain.json_types import JSONValue

log = logging.getLogger(__name__)

REAP_BATCH = 10_000  # rows looked at per kind per pass


@dataclass
class ReapResult:
    """Tasks moved by one reaper pass."""

    expired_retried: int = 0  # running -> pending (worker dead or lease expired, attempts left)
    expired_failed: int = 0  # running -> failed (worker dead or lease expired, no attempts left)
    expired_cancelled: int = 0  # running -> cancelled (job cancelled meanwhile)
    lost_requeued: int = 0  # queued -> pending (message lost)
    # of the running tasks moved, those whose worker was declared dead before the lease ran out
    dead_worker: int = 0

    @property
    def total(self) -> int:
        """All tasks moved."""
        return self.expired_retried + self.expired_failed + self.expired_cancelled + self.lost_requeued


_Cols = TypeVar("_Cols", bound=tuple[object, ...])
# (id, job_id, attempts, worker_id, lease_until, job state, job spec) of a running task of a lost worker
_ExpiredRow = Row[tuple[int, int, int, str | None, datetime | None, JobState, dict[str, JSONValue]]]


def _locked(session: Session, stmt: Select[_Cols]) -> Sequence[Row[_Cols]]:
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update(skip_locked=True, of=Task)
    return session.execute(stmt).all()


def _why(row: _ExpiredRow, now: datetime, dead_after_s: float | None) -> str:
    """How the worker of an expired row was lost, for the task's error text."""
    if row.lease_until is not None and row.lease_until < now:
        return f"LeaseExpired: worker {row.worker_id} stopped heart-beating (lost or killed)"
    return (
        f"WorkerDead: worker {row.worker_id} sent no heartbeat for over {dead_after_s:.0f} s (lost or killed)"
    )


def reap_once(
    session: Session, *, queued_timeout_s: float, now: datetime | None = None, default_max_attempts: int = 3,
    dead_after_s: float | None = None,
) -> ReapResult:
    """One reaper pass over dead workers' tasks, expired leases and lost queued tasks; commits. Returns the
    counts.

    `dead_after_s`: a worker whose last heartbeat is older than this, or that has no row, is dead for the
    tasks it started before then (None: leases only).
    """
    now = now or utcnow()
    res = ReapResult()
    _reap_running(session, res, now, default_max_attempts, dead_after_s)
    _requeue_lost(session, res, now, queued_timeout_s)
    session.commit()
    if res.total:
        log.info(
            "reaper: %d tasks of lost workers retried, %d failed, %d cancelled (%d of dead workers, before "
            "their lease ran out); %d lost queued tasks requeued",
            res.expired_retried, res.expired_failed, res.expired_cancelled, res.dead_worker,
            res.lost_requeued,
        )
    return res


def _reap_running(session: Session, res: ReapResult, now: datetime, default_max_attempts: int,
                  dead_after_s: float | None) -> None:
    """Running tasks of dead workers or expired leases: retried after a backoff, failed when out of attempts,
    cancelled with their job."""
    lost_worker = Task.lease_until < now
    if dead_after_s is not None:
        silent_since = now - timedelta(seconds=dead_after_s)
        # started_at too: a task claimed after the worker's last beat proves the worker was alive then
        silent = or_(Worker.last_heartbeat < silent_since, Worker.id.is_(None))
        lost_worker = or_(lost_worker, and_(silent, Task.started_at < silent_since))
    expired = _locked(
        session,
        select(Task.id, Task.job_id, Task.attempts, Task.worker_id, Task.lease_until, Job.state, Job.spec)
        .join(Job, Job.id == Task.job_id)
        .join(Worker, Worker.id == Task.worker_id, isouter=True)
        .where(Task.state == TaskState.RUNNING, lost_worker)
        .order_by(Task.id)
        .limit(REAP_BATCH),
    )
    res.dead_worker = sum(1 for r in expired if r.lease_until is None or r.lease_until >= now)
    by_job: dict[int, list[_ExpiredRow]] = defaultdict(list)
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
        retry: dict[tuple[float, str], list[int]] = defaultdict(list)
        fail: list[_ExpiredRow] = []
        for r in rows:
            if int(r.attempts) < max_attempts:
                retry[retry_backoff_s(int(r.attempts)), _why(r, now, dead_after_s)].append(int(r.id))
            else:
                fail.append(r)
        for (backoff, why), ids in retry.items():
            res.expired_retried += len(
                transition(
                    session, job_id=job_id, task_ids=ids, from_state=TaskState.RUNNING,
                    to_state=TaskState.PENDING, lease_until=None, worker_id=None, queued_at=None,
                    not_before=now + timedelta(seconds=backoff), error=f"{why}; retrying",
                )
            )
        for r in fail:  # one by one: each keeps its own error text (few: only tasks out of attempts)
            res.expired_failed += len(
                transition(
                    session, job_id=job_id, task_ids=[r.id], from_state=TaskState.RUNNING,
                    to_state=TaskState.FAILED, lease_until=None, finished_at=now,
                    error=(
                        f"{_why(r, now, dead_after_s)} while running this task; "
                        f"gave up after {r.attempts} attempt(s) (max_attempts={max_attempts})"
                    ),
                )
            )


def _requeue_lost(session: Session, res: ReapResult, now: datetime, queued_timeout_s: float) -> None:
    """Tasks queued longer than `queued_timeout_s` (their message was lost) go back to pending."""
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
        res.lost_requeued += len(
            transition(
                session, job_id=job_id, task_ids=ids, from_state=TaskState.QUEUED, to_state=TaskState.PENDING,
                queued_at=None,
            )
        )
