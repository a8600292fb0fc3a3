"""Which jobs a scheduler plans next: claims that share the planning slots fairly between tenants.

Planning a big job takes its slot (a planner process) for minutes, so the claim order decides how long a
tenant waits behind another's plans. A scheduler with free slots takes the waiting jobs in turns by tenant:
the tenant with the fewest plans under way (every scheduler's, from the live planner leases) goes next, ties
to the tenant whose oldest waiting job waited longest; within a tenant, higher priority first, then oldest.
A tenant's priority never outranks another tenant's jobs. So while others wait, a tenant holds no more
slots than its even share: tenant B's job is planned before tenant A's third, whatever A submitted first.
A slot already held for minutes is made free by the scheduler itself: a tenant with nothing planning
(`tenants_waiting_idle`) makes a scheduler whose slots are all busy pause one plan of a tenant holding several
(services.scheduler.planner_proc), and the claim order above then gives the freed slot to that tenant.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import ColumnElement, and_, func, or_, select, update
from sqlalchemy.orm import Session

from services.core.db.models import Job, JobState, utcnow
from services.core.db.states import check_job_edge

PLANNING_LEASE_S = 600  # a planner that holds a job longer than this without finishing is presumed dead


@dataclass(frozen=True)
class Waiting:
    """A job that may be claimed for planning."""

    job_id: int
    owner: str
    priority: int


def fair_plan_order(waiting: Sequence[Waiting], under_way: dict[str, int], limit: int) -> list[int]:
    """Up to `limit` job ids in the order to claim them: tenants in turns, fewest plans under way first."""
    queues: dict[str, list[Waiting]] = {}
    for job in sorted(waiting, key=lambda j: (-j.priority, j.job_id)):
        queues.setdefault(job.owner, []).append(job)
    load = {owner: under_way.get(owner, 0) for owner in queues}
    order: list[int] = []
    while len(order) < limit and queues:
        owner = min(queues, key=lambda o: (load[o], min(j.job_id for j in queues[o])))
        order.append(queues[owner].pop(0).job_id)
        load[owner] += 1
        if not queues[owner]:
            del queues[owner]
    return order


def _claimable(now: datetime) -> ColumnElement[bool]:
    """Pending jobs, and planning ones whose planner's lease ran out."""
    return or_(
        Job.state == JobState.PENDING,
        and_(
            Job.state == JobState.PLANNING,
            or_(Job.planner_lease_until.is_(None), Job.planner_lease_until < now),
        ),
    )


def _waiting(session: Session, now: datetime, limit: int) -> list[Waiting]:
    """Each tenant's first `limit` claimable jobs (priority, then age): enough for any fair order of
    `limit`."""
    rank = (
        func.row_number().over(partition_by=Job.owner, order_by=(Job.priority.desc(), Job.id)).label("rank")
    )
    ranked = select(Job.id, Job.owner, Job.priority, rank).where(_claimable(now)).subquery()
    rows = session.execute(
        select(ranked.c.id, ranked.c.owner, ranked.c.priority).where(ranked.c.rank <= limit)
    )
    return [Waiting(int(i), str(o), int(p)) for i, o, p in rows]


def _under_way(session: Session, now: datetime) -> dict[str, int]:
    """Plans in progress per tenant, on every scheduler (a live planner lease)."""
    rows = session.execute(
        select(Job.owner, func.count()).where(Job.state == JobState.PLANNING, Job.planner_lease_until >= now)
        .group_by(Job.owner)
    )
    return {str(owner): int(n) for owner, n in rows}


def claim_pending_jobs(
    session: Session, planner_id: str, limit: int = 1, *, now: datetime | None = None,
    lease_s: float = PLANNING_LEASE_S,
) -> list[Job]:
    """Claim up to `limit` jobs to plan, in the fair order above: pending ones, or planning ones whose
    planner's lease ran out.

    Postgres: each job is locked with FOR UPDATE SKIP LOCKED before it is taken, so concurrent schedulers
    never take the same job, nor wait on each other. SQLite: the conditional UPDATE alone lets only one
    claimer win. Claimed jobs are in state 'planning' with `planner = planner_id`; the caller commits.
    """
    now = now or utcnow()
    cond = _claimable(now)
    postgres = session.get_bind().dialect.name == "postgresql"
    claimed: list[int] = []
    for job_id in fair_plan_order(_waiting(session, now, limit), _under_way(session, now), limit=10**9):
        if len(claimed) >= limit:
            break
        lock = select(Job.state).where(Job.id == job_id, cond)
        seen = session.scalar(lock.with_for_update(skip_locked=True) if postgres else lock)
        if seen is None:  # taken (or being taken) by another scheduler
            continue
        check_job_edge(seen, JobState.PLANNING)
        res = session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == seen, cond)
            .values(
                state=JobState.PLANNING.value, planner=planner_id,
                planner_lease_until=now + timedelta(seconds=lease_s), started_at=now, error=None,
            )
            .execution_options(synchronize_session=False)
        )
        if res.rowcount == 1:  # type: ignore[attr-defined]
            claimed.append(job_id)
    if not claimed:
        return []
    jobs = {j.id: j for j in session.scalars(
        select(Job).where(Job.id.in_(claimed)).execution_options(populate_existing=True))}
    return [jobs[i] for i in claimed]


def tenants_waiting_idle(session: Session, now: datetime | None = None) -> set[str]:
    """Tenants with a job waiting to be planned and no plan under way on any scheduler."""
    now = now or utcnow()
    waiting = {str(owner) for owner in session.scalars(select(Job.owner).where(_claimable(now)).distinct())}
    return waiting - set(_under_way(session, now)) if waiting else set()
