"""Dispatch: pick ready tasks (cue DAG satisfied), mark them queued, commit, then send them.

A pending task is ready when its `not_before` has passed and every input cue task of the same
(job, space, point, view) is done (per-point inputs: the point's view 0). Readiness is checked in SQL
per cue: an ordered scan of the cue's pending tasks (index job_id, state, cue, id) with a correlated
lookup of the inputs' states over the task table's unique index. The counters bound each scan: cue c
can have at most min(done inputs) - (c tasks no longer pending) ready tasks, and at most the number of
in-flight or failed input tasks of blocked ones ahead of them, so a pass never walks the thousands of
tasks whose inputs have not even started. A task whose input failed for good can never run: it fails
too ("UpstreamFailed"), so the job can finish.

Each running job keeps at most `window` tasks queued + running (counters, never COUNT(*)). Tenants
split the pass budget evenly; within a tenant jobs are served by priority (higher first, strictly) and
jobs of equal priority split evenly, each from a rotating position (round robin; `fairness` module). Ready
tasks of a job go out oldest (lowest id) first, which is view by view: a view's derived cues before the next
view's render. Postgres and SQLite.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import ColumnElement, case, func, literal, literal_column, or_, select, text
from sqlalchemy.orm import Session

from services.core.db.models import Job, JobCounter, JobState, Task, TaskState, utcnow
from services.core.db.states import transition
from services.core.domain.cues import CATALOG
from services.scheduler.fairness import queued_now, tenant_turns
from services.scheduler.job_load import INFLIGHT, JobLoad
from services.scheduler.transport import Transport

log = logging.getLogger(__name__)

DEFAULT_BUDGET = 20_000  # tasks dispatched per pass at most (bounds one transaction)
SEND_CHUNK = 1_000  # tasks per transport.send call: the first messages reach workers while the rest are built
SCAN_MARGIN = 64  # extra rows looked at per cue beyond what the counters predict
# the pending-task index is partial (migration 0004): scans name its predicate's literal
PENDING_LITERAL: ColumnElement[str] = literal_column(f"'{TaskState.PENDING.value}'")
SCAN_CAP = 200_000  # rows looked at per cue and pass at most
# Rows per cue a thorough pass (the safety net, every minute) reads, oldest first: each costs a lookup of its
# inputs, so reading up to SCAN_CAP of every cue took 17 s a pass on a 620k-task job under load and would take
# minutes on a starter-sized one (bench/scale/scale_sim.py, bench/scale/big_job.py). Ready tasks are the
# oldest ones.
THOROUGH_SCAN_ROWS = 10_000
UPSTREAM_FAILED = (TaskState.FAILED, TaskState.CANCELLED)


@dataclass
class DispatchResult:
    """What one dispatch pass did: tasks sent per job, put back after a failed send, failed upstream."""

    per_job: dict[int, int] = field(default_factory=dict)
    requeued: int = 0
    upstream_failed: int = 0
    stalled: list[int] = field(default_factory=list)  # jobs with pending tasks, none ready, none in flight
    capped: bool = False  # the broker queue's cap, not the ready tasks, bounded the pass
    settled: bool = False  # some running job had nothing pending, queued or running: completion has work

    @property
    def sent(self) -> int:
        """Number of tasks handed to the transport."""
        return sum(self.per_job.values())


def running_job_loads(session: Session) -> list[JobLoad]:
    """Every running job with its counters and tenant, highest priority first."""
    c = JobCounter.__table__.c
    summed = (  # the shards summed in SQL: ~100 rows a job reach Python instead of ~1,500
        select(c.job_id, c.cue, c.state, func.sum(c.n).label("n"))
        .where(c.job_id.in_(select(Job.id).where(Job.state == JobState.RUNNING)))
        .group_by(c.job_id, c.cue, c.state)
        .subquery()
    )
    rows = session.execute(
        select(Job.id, Job.priority, Job.owner, summed.c.cue, summed.c.state, summed.c.n)
        .join(summed, summed.c.job_id == Job.id, isouter=True)
        .where(Job.state == JobState.RUNNING)
    ).all()
    loads: dict[int, JobLoad] = {}
    for job_id, prio, owner, cue, state, n in rows:
        load = loads.setdefault(int(job_id), JobLoad(int(job_id), int(prio or 0), owner=str(owner or "")))
        if cue is not None and n:
            load.counts.setdefault(str(cue), {})[str(state)] = int(n)
    return sorted(loads.values(), key=lambda j: (-j.priority, j.job_id))


def _input_rank(cue: str, t: Any, i: Any) -> Any:
    """Correlated SQL scalar: 0/NULL all inputs done, 1 an input not done yet, 2 an input failed or
    cancelled."""
    inputs = CATALOG[cue].inputs
    view_inputs = [c for c in inputs if not CATALOG[c].per_point]
    point_inputs = [c for c in inputs if CATALOG[c].per_point]
    which = []
    if view_inputs:
        which.append((i.view_idx == t.view_idx) & i.cue.in_(view_inputs))
    if point_inputs:  # per-point cues exist on view 0 only
        which.append((i.view_idx == 0) & i.cue.in_(point_inputs))
    rank = case((i.state == TaskState.DONE, 0), (i.state.in_(UPSTREAM_FAILED), 2), else_=1)
    return (
        select(func.max(rank))
        .where(i.job_id == t.job_id, i.space_id == t.space_id, i.point_idx == t.point_idx, or_(*which))
        .scalar_subquery()
    )


def scan_cue(
    session: Session, job_id: int, cue: str, want: int, now: datetime, max_rows: int = SCAN_CAP,
) -> tuple[list[int], list[int]]:
    """Oldest-first pending tasks of one cue: (up to `want` ready ids, ids whose input failed for good).

    Reads pages (doubling in size) until `want` ready tasks are found, the cue has no more pending
    tasks, or `max_rows` rows were read.
    """
    if max_rows <= 0:
        return [], []
    t = Task.__table__.alias("t")
    i = Task.__table__.alias("i")
    rank = _input_rank(cue, t.c, i.c) if CATALOG[cue].inputs else literal(0)
    base = select(t.c.id, rank).where(
        t.c.job_id == job_id,
        # inline, as the partial index's predicate (a bound value would not match it)
        t.c.state == PENDING_LITERAL,
        t.c.cue == cue,
        or_(t.c.not_before.is_(None), t.c.not_before <= now),
    )
    if session.get_bind().dialect.name == "postgresql":
        # Concurrent schedulers take disjoint tasks instead of queueing behind each other's row locks.
        base = base.with_for_update(of=t, skip_locked=True)
    ready: list[int] = []
    doomed: list[int] = []
    last = 0
    scanned = 0
    page = min(max_rows, max(want, 1) + SCAN_MARGIN)
    while scanned < max_rows:
        rows = session.execute(base.where(t.c.id > last).order_by(t.c.id).limit(page)).all()
        for tid, r in rows:
            if not r:
                ready.append(int(tid))
            elif r == 2:
                doomed.append(int(tid))
        scanned += len(rows)
        if len(rows) < page or len(ready) >= want:
            break
        last = int(rows[-1][0])
        page = min(2 * page, max_rows - scanned)
    return ready[:want], doomed


def ready_tasks(
    session: Session, job_id: int, limit: int, now: datetime | None = None, load: JobLoad | None = None,
    thorough: bool = False,
) -> tuple[list[tuple[int, str]], list[int]]:
    """Up to `limit` ready (task_id, cue) pairs of the job, oldest first, and ids that failed upstream.

    With `load` (the job's counters) cues that cannot have ready tasks are skipped and scans are
    bounded; `thorough` (or no load) scans every cue with pending tasks up to THOROUGH_SCAN_ROWS rows.
    """
    now = now or utcnow()
    if limit <= 0:
        return [], []
    if load is None:
        thorough = True
        load = next((j for j in _loads_of(session, [job_id])), JobLoad(job_id, 0))
    plans: list[tuple[str, int, int]] = []  # (cue, ready wanted, rows to read at most)
    for cue, per in load.counts.items():
        if not per.get(TaskState.PENDING) or cue not in CATALOG:
            continue
        inputs = CATALOG[cue].inputs
        if not inputs:
            plans.append((cue, limit, limit))
        elif thorough:
            plans.append((cue, limit, THOROUGH_SCAN_ROWS))
        else:
            # ready <= views whose inputs are done minus this cue's tasks already past pending;
            # rows ahead of them are blocked by in-flight inputs or doomed by failed ones.
            past_pending = sum(n for s, n in per.items() if s != TaskState.PENDING)
            possible = min(load.n(x, TaskState.DONE) for x in inputs) - past_pending
            failed_inputs = sum(load.n(x, *UPSTREAM_FAILED) for x in inputs)
            undoomed = failed_inputs - per.get(TaskState.FAILED, 0)
            if possible <= 0 and undoomed <= 0:
                continue  # every pending task of this cue waits for an input that has not finished
            blocked_ahead = sum(load.n(x, *INFLIGHT) for x in inputs) + max(undoomed, 0)
            plans.append((cue, max(possible, 0), blocked_ahead + SCAN_MARGIN))
    # Share `limit` among the cues in proportion to what each can give, so a pass reads about `limit`
    # ready rows in all instead of `limit` per cue (derived cues cost a correlated lookup per row).
    total = sum(w for _, w, _ in plans)
    candidates: list[tuple[int, str]] = []
    doomed: list[int] = []
    for cue, possible, extra in plans:
        if thorough or not CATALOG[cue].inputs:
            want, max_rows = possible, extra
        else:
            want = min(possible, -(-limit * possible // total)) if total > limit else possible
            max_rows = want + extra
        ready, failed = scan_cue(session, job_id, cue, want, now, max_rows)
        candidates.extend((tid, cue) for tid in ready)
        doomed.extend(failed)
    candidates.sort()
    return candidates[:limit], doomed


def _loads_of(session: Session, job_ids: list[int]) -> list[JobLoad]:
    c = JobCounter.__table__.c
    loads: dict[int, JobLoad] = {j: JobLoad(j, 0) for j in job_ids}
    for job_id, cue, state, n in session.execute(
        select(c.job_id, c.cue, c.state, c.n).where(c.job_id.in_(job_ids), c.n != 0)
    ):
        per = loads[int(job_id)].counts.setdefault(str(cue), {})
        per[str(state)] = per.get(str(state), 0) + int(n)  # summed over the counter shards
    return list(loads.values())


def dispatch_once(
    session: Session,
    transport: Transport,
    *,
    window: int,
    budget: int = DEFAULT_BUDGET,
    rotation: int = 0,
    now: datetime | None = None,
    thorough: bool = False,
    queued_cap: int | None = None,
) -> DispatchResult:
    """One dispatch pass: mark up to `budget` ready tasks queued, COMMIT, then send them.

    Within a priority group each job gets an even share of what is left of the budget (jobs after it
    inherit what it could not use). If a send fails, its tasks go back to pending at once (a duplicate
    of a message that did get through is harmless: the worker's claim needs state 'queued'); if even
    that fails, the reaper puts them back after the lease time. `thorough` ignores the counter-based
    scan bounds (the loop does this now and then as a safety net). `queued_cap` bounds the tasks queued
    (sent, not claimed) over all jobs after the pass.
    """
    now = now or utcnow()
    if session.get_bind().dialect.name == "postgresql":
        # The scans are cheap index walks; the planner's cost estimates would trigger a slow JIT compile.
        session.execute(text("SET LOCAL jit = off"))
    result = DispatchResult()
    picked: list[tuple[int, list[tuple[int, str]]]] = []
    loads = running_job_loads(session)
    result.settled = any(load.pending == 0 and load.inflight == 0 for load in loads)
    if queued_cap is not None and queued_cap - queued_now(loads) < budget:
        # a short broker queue: a newcomer waits behind few others
        budget = max(0, queued_cap - queued_now(loads))
        result.capped = True
    tenants = tenant_turns(loads, window, rotation)
    for t, groups in enumerate(tenants):
        share = -(-budget // (len(tenants) - t))  # ceil: what earlier tenants could not use carries over
        for group in groups:  # strict priority within the tenant
            for k, load in enumerate(group):
                if share <= 0:
                    break
                take = min(-(-share // (len(group) - k)), window - load.inflight)
                moved = _pick(session, load, take, now, thorough, result)
                if moved:
                    picked.append((load.job_id, moved))
                    share -= len(moved)
                    budget -= len(moved)
    session.commit()  # queued is durable before any message exists
    _send(session, transport, picked, result)
    return result


def _send(session: Session, transport: Transport, picked: list[tuple[int, list[tuple[int, str]]]],
          result: DispatchResult) -> None:
    """Send the queued tasks in chunks; after one failed send the broker is presumed down and the rest go
    back to pending unsent."""
    broken = False
    for job_id, moved in picked:
        for k in range(0, len(moved), SEND_CHUNK):
            part = moved[k : k + SEND_CHUNK]
            if not broken:
                try:
                    transport.send(part)
                    result.per_job[job_id] = result.per_job.get(job_id, 0) + len(part)
                    continue
                except Exception:
                    broken = True
                    log.exception(
                        "sending tasks of job %d failed; putting the unsent ones back to pending", job_id
                    )
            result.requeued += _unqueue(session, job_id, part)


def _pick(
    session: Session, load: JobLoad, take: int, now: datetime, thorough: bool, result: DispatchResult,
) -> list[tuple[int, str]]:
    """Mark up to `take` ready tasks of one job queued (not committed); fails those whose input failed for
    good."""
    ready, doomed = ready_tasks(session, load.job_id, take, now, load, thorough)
    if doomed:
        result.upstream_failed += len(
            transition(
                session, job_id=load.job_id, task_ids=doomed, from_state=TaskState.PENDING,
                to_state=TaskState.FAILED, finished_at=now,
                error="UpstreamFailed: an input cue task of this view failed or was cancelled",
            )
        )
    if not ready:
        if load.inflight == 0 and not doomed:
            result.stalled.append(load.job_id)
        return []
    return transition(
        session, job_id=load.job_id, task_ids=[tid for tid, _ in ready],
        from_state=TaskState.PENDING, to_state=TaskState.QUEUED, queued_at=now,
    )


def _unqueue(session: Session, job_id: int, moved: list[tuple[int, str]]) -> int:
    try:
        back = transition(
            session, job_id=job_id, task_ids=[tid for tid, _ in moved],
            from_state=TaskState.QUEUED, to_state=TaskState.PENDING, queued_at=None,
        )
        session.commit()
        return len(back)
    except Exception:
        session.rollback()
        log.exception("could not put job %d's unsent tasks back; the reaper will", job_id)
        return 0
