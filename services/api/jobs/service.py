"""Job logic: create, list, progress (from JobCounter rows only), lifecycle actions, delete.

Progress never counts task rows: it reads the job's handful of `job_counter` rows, so GET /jobs/{id} costs
the same on a 1M-task job as on a 10-task one. Throughput is measured from successive counter readings
kept in memory (RateTracker), falling back to the average since the job started.
"""

from __future__ import annotations

import functools
import json
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import Any

from fastapi import HTTPException, status
from sqlalchemy import bindparam, func, select
from sqlalchemy.orm import Session, defer

from services.api.jobs.schemas import (
    CueProgress,
    JobCreate,
    JobDetail,
    JobEvent,
    JobRead,
    JobSpaceRead,
    Progress,
)
from services.api.pagination import PageParams
from services.api.spaces.service import not_found
from services.core import jobs as core_jobs
from services.core.cues import CATALOG
from services.core.db import summed_counters
from services.core.models import (
    JOB_TERMINAL_STATES,
    TASK_ACTIVE_STATES,
    TASK_STATES,
    TASK_TERMINAL_STATES,
    Job,
    JobSpace,
    JobState,
    Space,
    TaskState,
    utcnow,
)
from services.core.spaces import frame_of
from services.core.storage import ObjectStore

FINISHED_STATES = TASK_TERMINAL_STATES
REMAINING_STATES = TASK_ACTIVE_STATES

Counters = dict[str, dict[str, int]]  # cue -> state -> n
STALL_MIN_S = 10.0  # a running job that finished nothing for this long, and ...
STALL_INTERVALS = 5.0  # ... for this many of its mean intervals between finishes, has no ETA
_CUE_ORDER = {name: i for i, name in enumerate(CATALOG)}


class RateTracker:
    """Recent finish rate per job from successive counter readings (thread-safe, bounded memory)."""

    def __init__(self, window_s: float = 60.0, min_span_s: float = 2.0, max_jobs: int = 10_000):
        self.window_s = window_s
        self.min_span_s = min_span_s
        self.max_jobs = max_jobs
        self._samples: dict[int, deque[tuple[float, int, int]]] = {}
        self._lock = threading.Lock()

    def observe(self, job_id: int, finished: int, labels: int, now: float | None = None) -> tuple[float, float] | None:
        """Record a reading (monotonic seconds); return (tasks/s, labels/s) over the window, or None if too short."""
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._samples.get(job_id)
            if q is None:
                if len(self._samples) >= self.max_jobs:
                    self._evict(now)
                q = self._samples[job_id] = deque()
            if not q or now - q[-1][0] >= 0.2 or q[-1][1] != finished:
                q.append((now, finished, labels))
            # Keep one sample older than the window so the rate always spans the whole window.
            while len(q) > 2 and now - q[1][0] >= self.window_s:
                q.popleft()
            t0, n0, l0 = q[0]
            t1, n1, l1 = q[-1]
            if t1 - t0 < self.min_span_s:
                return None
            if n1 < n0:  # counters went down (retry of failed tasks): restart the window
                q.clear()
                q.append((t1, n1, l1))
                return None
            return (n1 - n0) / (t1 - t0), max(0, l1 - l0) / (t1 - t0)

    def idle_s(self, job_id: int, now: float | None = None) -> float:
        """Seconds since the job's finished count last changed, as far as the kept readings tell (0 if unknown)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._samples.get(job_id)
            if not q:
                return 0.0
            since = q[0][0]
            for k in range(len(q) - 1, 0, -1):
                if q[k - 1][1] != q[k][1]:
                    since = q[k][0]
                    break
            return max(0.0, now - since)

    def _evict(self, now: float) -> None:
        stale = [j for j, q in self._samples.items() if not q or now - q[-1][0] > self.window_s]
        for j in stale or list(self._samples)[: len(self._samples) // 2]:
            del self._samples[j]


def read_counters(session: Session, job_ids: Sequence[int]) -> dict[int, Counters]:
    """Counters of several jobs in one query: {job_id: {cue: {state: n}}} (zero rows omitted)."""
    out: dict[int, Counters] = {j: {} for j in job_ids}
    if not job_ids:
        return out
    rows = session.execute(summed_counters(list(job_ids)))
    for job_id, cue, state, n in rows:
        out[int(job_id)].setdefault(cue, {})[state] = int(n)
    return out


def _by_state(counts: dict[str, int]) -> dict[str, int]:
    return {s: int(counts.get(s, 0)) for s in TASK_STATES}


def compute_progress(
    job: Job, counters: Counters, rates: RateTracker | None, now: datetime | None = None
) -> tuple[Progress, dict[str, CueProgress]]:
    """Overall and per-cue progress of `job` from its counters; throughput and ETA from `rates`."""
    totals: dict[str, int] = dict.fromkeys(TASK_STATES, 0)
    cues: dict[str, CueProgress] = {}
    labels_done = 0
    for cue in sorted(counters, key=lambda c: _CUE_ORDER.get(c, len(_CUE_ORDER))):
        by = _by_state(counters[cue])
        total = sum(by.values())
        fin = sum(by[s] for s in FINISHED_STATES)
        for s, n in by.items():
            totals[s] += n
        if cue in CATALOG and not CATALOG[cue].internal:
            labels_done += by[TaskState.DONE]
        cues[cue] = CueProgress(by_state=by, total=total, done=by[TaskState.DONE], fraction=fin / total if total else 0.0)
    total = sum(totals.values())
    finished = sum(totals[s] for s in FINISHED_STATES)
    remaining = sum(totals[s] for s in REMAINING_STATES)
    if total:
        fraction = finished / total
    else:
        fraction = 1.0 if job.state == JobState.DONE else 0.0

    rate: float | None = None
    label_rate: float | None = None
    recent = rates.observe(job.id, finished, labels_done) if rates is not None and job.state == JobState.RUNNING else None
    if recent is not None:
        rate, label_rate = recent
    elif job.started_at is not None and finished:
        end = job.finished_at if job.state in JOB_TERMINAL_STATES and job.finished_at else (now or utcnow())
        span = (end - job.started_at).total_seconds()
        if span > 0:
            rate, label_rate = finished / span, labels_done / span
    eta: float | None = None
    if job.state in JOB_TERMINAL_STATES:
        eta = 0.0 if job.state == JobState.DONE else None
    elif job.state == JobState.RUNNING and rate and rate > 0:
        eta = remaining / rate
        # No task finished for much longer than the rate predicts (a dead worker's task waits for the reaper):
        # the ETA is unknown, not the few seconds the old rate would promise.
        if rates is not None and rates.idle_s(job.id) > max(STALL_MIN_S, STALL_INTERVALS / rate):
            eta = None
    progress = Progress(
        total=total,
        by_state=totals,
        finished=finished,
        fraction=round(fraction, 6),
        throughput_per_s=None if rate is None else round(rate, 4),
        labels_per_s=None if label_rate is None else round(label_rate, 4),
        eta_s=None if eta is None else round(eta, 1),
    )
    return progress, cues


def _space_ids(session: Session, job_ids: Sequence[int]) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {j: [] for j in job_ids}
    if not job_ids:
        return out
    rows = session.execute(
        select(JobSpace.job_id, JobSpace.space_id)
        .where(JobSpace.job_id.in_(list(job_ids)))
        .order_by(JobSpace.job_id, JobSpace.position)
    )
    for job_id, space_id in rows:
        out[int(job_id)].append(int(space_id))
    return out


def job_read(job: Job, counters: Counters, space_ids: list[int], rates: RateTracker | None) -> JobRead:
    """The list view of a job."""
    progress, cues = compute_progress(job, counters, rates)
    return JobRead(
        id=job.id,
        name=job.name,
        state=job.state,
        priority=job.priority,
        error=job.error,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        total_tasks=job.total_tasks,
        space_ids=space_ids,
        progress=progress,
        cues=cues,
    )


def job_event(job: Job, counters: Counters, rates: RateTracker | None) -> JobEvent:
    """What an SSE client gets for a job."""
    progress, cues = compute_progress(job, counters, rates)
    return JobEvent(id=job.id, name=job.name, state=job.state, error=job.error, progress=progress, cues=cues)


def get_job(session: Session, *, owner: str, job_id: int) -> Job:
    """The tenant's job, or 404 (also for another tenant's job)."""
    job = session.get(Job, job_id)
    if job is None or job.owner != owner:
        raise not_found("job", job_id)
    return job


def _json_list(value: Any) -> list[Any]:
    # Postgres' json_agg arrives parsed; SQLite's json_group_array arrives as text; no rows gives NULL.
    if value is None:
        return []
    return list(json.loads(value)) if isinstance(value, str) else list(value)


@functools.cache
def detail_statement(dialect: str) -> Any:
    """SELECT job + counters + spaces (json aggregates) for one job and owner; built once per dialect, so
    SQLAlchemy's memoized cache key is reused instead of re-traversing the statement on every poll."""
    agg, arr = (func.json_agg, func.json_build_array) if dialect == "postgresql" else (func.json_group_array, func.json_array)
    js, t = JobSpace.__table__.c, Job.__table__.c
    summed = summed_counters(t.id).subquery()  # the counter shards of the job, summed
    counters_q = select(agg(arr(summed.c.cue, summed.c.state, summed.c.n))).scalar_subquery()
    spaces_q = (
        select(agg(arr(js.space_id, Space.name, js.position, js.cues)))
        .select_from(JobSpace.__table__.join(Space, Space.id == js.space_id))
        .where(js.job_id == t.id)
        .scalar_subquery()
    )
    return select(*t, counters_q.label("counters"), spaces_q.label("spaces")).where(
        t.id == bindparam("job_id"), t.owner == bindparam("owner")
    )


def fetch_job_detail(session: Session, *, owner: str, job_id: int, rates: RateTracker | None) -> JobDetail:
    """The tenant's job with spaces and progress in ONE statement (the hot path of progress polling); 404."""
    stmt = detail_statement(session.get_bind().dialect.name)
    row = session.execute(stmt, {"job_id": job_id, "owner": owner}).first()
    if row is None:
        raise not_found("job", job_id)
    counters: Counters = {}
    for cue, state, n in _json_list(row.counters):
        counters.setdefault(cue, {})[state] = int(n)
    planned = (row.plan_summary or {}).get("spaces", {})
    spaces = sorted(
        (
            JobSpaceRead(space_id=int(sid), name=name, position=int(pos), cues=list(cues if isinstance(cues, list) else json.loads(cues)),
                         frame=frame_of(planned.get(name)))
            for sid, name, pos, cues in _json_list(row.spaces)
        ),
        key=lambda sp: (sp.position, sp.space_id),
    )
    base = job_read(row, counters, [sp.space_id for sp in spaces], rates)  # type: ignore[arg-type]
    return JobDetail(
        **base.model_dump(), spec=row.spec, spaces=spaces, output_root=row.output_root, plan_summary=row.plan_summary
    )


def job_detail(session: Session, job: Job, rates: RateTracker | None) -> JobDetail:
    """A job with its spec, spaces, plan summary and progress."""
    return fetch_job_detail(session, owner=job.owner, job_id=job.id, rates=rates)


def list_jobs(
    session: Session, *, owner: str, states: Sequence[str] | None, page: PageParams, rates: RateTracker | None
) -> tuple[list[JobRead], int]:
    """The tenant's jobs (newest first), optionally only in `states`, with progress; and the filtered total."""
    cond = [Job.owner == owner]
    if states:
        cond.append(Job.state.in_(list(states)))
    total = session.scalar(select(func.count()).select_from(Job).where(*cond)) or 0
    jobs = session.scalars(
        select(Job)
        .options(defer(Job.spec), defer(Job.plan_summary))  # specs can hold thousands of provided poses
        .where(*cond)
        .order_by(Job.id.desc())
        .limit(page.limit)
        .offset(page.offset)
    ).all()
    ids = [j.id for j in jobs]
    counters = read_counters(session, ids)
    spaces = _space_ids(session, ids)
    return [job_read(j, counters[j.id], spaces[j.id], rates) for j in jobs], int(total)


def create_job(session: Session, *, owner: str, body: JobCreate) -> Job:
    """Create a pending job over the tenant's spaces; 404 for a space that is not theirs, 422 for a cue it lacks."""
    found = {
        s.id: s
        for s in session.scalars(select(Space).where(Space.id.in_(body.space_ids), Space.owner == owner)).all()
    }
    missing = [i for i in body.space_ids if i not in found]
    if missing:
        raise not_found("space" if len(missing) == 1 else "spaces", ", ".join(map(str, missing)))
    try:
        job = core_jobs.create_job(session, owner=owner, spec=body.spec, spaces=[found[i] for i in body.space_ids])
    except ValueError as e:
        session.rollback()
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(e)) from None
    session.commit()
    return job


ACTIONS: dict[str, Callable[[Session, Job], Any]] = {
    "cancel": core_jobs.cancel_job,
    "pause": core_jobs.pause_job,
    "resume": core_jobs.resume_job,
    "retry": core_jobs.retry_failed,
}


def apply_action(session: Session, *, owner: str, job_id: int, action: str) -> Job:
    """Run a lifecycle action (cancel, pause, resume, retry) on the tenant's job; 409 if its state forbids it."""
    job = get_job(session, owner=owner, job_id=job_id)
    try:
        ACTIONS[action](session, job)
    except core_jobs.JobStateError as e:
        session.rollback()
        raise HTTPException(status.HTTP_409_CONFLICT, str(e)) from None
    session.commit()
    session.refresh(job)
    return job


def delete_job(session: Session, store: ObjectStore, *, owner: str, job_id: int) -> None:
    """Delete the tenant's job with its outputs (an unfinished job is cancelled first)."""
    job = get_job(session, owner=owner, job_id=job_id)
    core_jobs.delete_job(session, store, job)
    session.commit()
