"""Who gets the next dispatched tasks: tenants share evenly, priority counts only within a tenant.

The broker's queues are first-in first-out and shared by every job, so the order the scheduler sends in is
the order workers run in. Two rules keep one tenant's big job from delaying another's small one by its whole
length:

- fair shares: each dispatch pass splits its budget evenly between the tenants that have work (round robin
  from a rotating start, what one cannot use goes to the next); inside a tenant, higher priority goes first
  and jobs of equal priority split evenly. A tenant's priority never outranks another tenant's work.
- a short queue: while live workers are known, the tasks queued in the broker (sent, not yet claimed) are
  capped at a few per live worker (`queued_cap`), so a newcomer's tasks wait behind that many, not behind the
  thousands a job's window allows. Without worker rows (the embedded runner, tests) nothing is capped.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timedelta
from itertools import groupby

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.db.models import TaskState, Worker, utcnow
from services.scheduler.job_load import JobLoad

# tasks waiting in the broker per live worker (the loop tops the queue up every CAPPED_WAIT_S)
QUEUED_PER_WORKER = 2
QUEUED_MIN = 8  # ... and at least this many, so a fleet of one or two workers never starves between passes
CAPPED_WAIT_S = 0.1  # the loop's pause while the queue is at its cap (instead of its idle interval)


def tenant_turns(loads: Sequence[JobLoad], window: int, rotation: int = 0) -> list[list[list[JobLoad]]]:
    """Eligible jobs as tenants (rotated) -> priority groups (highest first) -> jobs (rotated within a
    group)."""
    eligible = [j for j in loads if j.pending > 0 and j.inflight < window]
    by_tenant: dict[str, list[JobLoad]] = {}
    for load in sorted(eligible, key=lambda j: (j.owner, -j.priority, j.job_id)):
        by_tenant.setdefault(load.owner, []).append(load)
    tenants = []
    for jobs in by_tenant.values():
        groups = []
        for _prio, grp in groupby(jobs, key=lambda j: j.priority):
            members = list(grp)
            k = rotation % len(members)
            groups.append(members[k:] + members[:k])
        tenants.append(groups)
    if tenants:
        k = rotation % len(tenants)
        tenants = tenants[k:] + tenants[:k]
    return tenants


def queued_now(loads: Sequence[JobLoad]) -> int:
    """Tasks sent and not yet claimed, over every running job (from the counters)."""
    return sum(per.get(TaskState.QUEUED, 0) for load in loads for per in load.counts.values())


def queued_cap(session: Session, *, alive_within_s: float, now: datetime | None = None) -> int | None:
    """How many tasks may wait in the broker: QUEUED_PER_WORKER per live worker (at least QUEUED_MIN), or None
    when no worker has beaten within `alive_within_s` (nothing to size the queue by: no cap)."""
    now = now or utcnow()
    live = int(
        session.scalar(
            select(func.count())
            .select_from(Worker)
            .where(Worker.last_heartbeat > now - timedelta(seconds=alive_within_s))
        )
        or 0
    )
    return max(QUEUED_MIN, QUEUED_PER_WORKER * live) if live else None
