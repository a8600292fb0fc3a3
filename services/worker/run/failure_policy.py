"""What a worker does after a task fails: retry after a backoff, and keep a failing worker off a job.

A task goes back to pending with a growing backoff while attempts < the job's max_attempts, else it fails for
good. A worker that failed BLOCK_AFTER_FAILURES times on one job (a broken GPU, a full disk) is kept off that
job for BLOCK_FOR, so the job's tasks go to healthy workers instead of burning their attempts on this one; a
blocked worker hands a claimed task back after HANDBACK_DELAY so that others get it first.
"""

from __future__ import annotations

import logging
from datetime import datetime, timedelta

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from services.core.db.jobs import retry_backoff_s
from services.core.db.models import WorkerBlock

log = logging.getLogger(__name__)

BLOCK_AFTER_FAILURES = 3  # failures of one worker on one job before it is kept off that job
BLOCK_FOR = timedelta(minutes=10)
HANDBACK_DELAY = timedelta(seconds=1)  # a blocked worker's hand-back waits a little, so others get it first


def retry_delay(attempts: int) -> timedelta:
    """How long a task that failed on attempt `attempts` waits in pending before it is dispatched again."""
    return timedelta(seconds=retry_backoff_s(attempts))


def is_blocked(s: Session, worker_id: str, job_id: int, now: datetime) -> bool:
    """Whether `worker_id` is kept off `job_id` at `now`."""
    return s.execute(
        select(WorkerBlock.job_id).where(
            WorkerBlock.worker_id == worker_id, WorkerBlock.job_id == job_id,
            or_(WorkerBlock.until.is_(None), WorkerBlock.until > now),
        )
    ).first() is not None


def count_failure(s: Session, worker_id: str, job_id: int, now: datetime) -> None:
    """One more failure of this worker on the job; every BLOCK_AFTER_FAILURES-th keeps it off for a while."""
    block = s.get(WorkerBlock, (worker_id, job_id))
    if block is None:
        # `until` None would mean "for good": an unblocked row carries a time in the past.
        block = WorkerBlock(worker_id=worker_id, job_id=job_id, failures=0, until=now)
        s.add(block)
    block.failures = int(block.failures or 0) + 1
    if block.failures % BLOCK_AFTER_FAILURES == 0:
        block.until = now + BLOCK_FOR
        log.warning("worker %s failed %d times on job %d: kept off it until %s", worker_id,
                    block.failures, job_id, block.until.isoformat())
