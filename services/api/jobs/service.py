"""Job logic: create, list, read with progress (services.api.jobs.progress), lifecycle actions, delete."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Sequence
from typing import Any

from sqlalchemy import Executable, bindparam, func, select
from sqlalchemy.orm import Session, defer

from services.api.jobs.progress import Counters, compute_progress, read_counters
from services.api.jobs.rates import RateTracker
from services.api.jobs.schemas import (
    JobCreate,
    JobDetail,
    JobEvent,
    JobRead,
    JobSpaceRead,
)
from services.api.pagination import PageParams
from services.api.spaces.service import not_found
from services.core.db import jobs as core_jobs
from services.core.db.counters import summed_counters
from services.core.db.models import (
    Job,
    JobSpace,
    Space,
)
from services.core.domain.errors import Conflict, Invalid
from services.core.domain.plan_budget import DEFAULT_CHUNK_VIEWS, check_plan_budget
from services.core.ingest.frame.resolve import frame_of
from services.core.storage import ObjectStore


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
        paused_by=job.paused_by,
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


def _json_list(value: Any) -> list[Any]:  # a JSON aggregate's rows, as the driver returns them (untyped)
    # Postgres' json_agg arrives parsed; SQLite's json_group_array arrives as text; no rows gives NULL.
    if value is None:
        return []
    return list(json.loads(value)) if isinstance(value, str) else list(value)


@functools.cache
def detail_statement(dialect: str) -> Executable:
    """SELECT job + counters + spaces (json aggregates) for one job and owner; built once per dialect, so
    SQLAlchemy's memoized cache key is reused instead of re-traversing the statement on every poll."""
    agg, arr = (
        (func.json_agg, func.json_build_array)
        if dialect == "postgresql"
        else (func.json_group_array, func.json_array)
    )
    job_space_cols, t = JobSpace.__table__.c, Job.__table__.c
    summed = summed_counters(t.id).subquery()  # the counter shards of the job, summed
    counters_q = select(agg(arr(summed.c.cue, summed.c.state, summed.c.n))).scalar_subquery()
    spaces_q = (
        select(agg(arr(job_space_cols.space_id, Space.name, job_space_cols.position, job_space_cols.cues)))
        .select_from(JobSpace.__table__.join(Space, Space.id == job_space_cols.space_id))
        .where(job_space_cols.job_id == t.id)
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
            JobSpaceRead(
                space_id=int(sid), name=name, position=int(pos),
                cues=list(cues if isinstance(cues, list) else json.loads(cues)),
                frame=frame_of(planned.get(name)),
            )
            for sid, name, pos, cues in _json_list(row.spaces)
        ),
        key=lambda space: (space.position, space.space_id),
    )
    base = job_read(row, counters, [space.space_id for space in spaces], rates)  # type: ignore[arg-type]
    return JobDetail(
        **base.model_dump(),
        spec=row.spec, spaces=spaces, output_root=row.output_root, plan_summary=row.plan_summary,
    )


def job_detail(session: Session, job: Job, rates: RateTracker | None) -> JobDetail:
    """A job with its spec, spaces, plan summary and progress."""
    return fetch_job_detail(session, owner=job.owner, job_id=job.id, rates=rates)


def list_jobs(
    session: Session, *, owner: str, states: Sequence[str] | None, page: PageParams, rates: RateTracker | None
) -> tuple[list[JobRead], int]:
    """The tenant's jobs (newest first), optionally only in `states`, with progress; and the filtered
    total."""
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


def create_job(
    session: Session,
    *,
    owner: str, body: JobCreate, plan_memory_mb: int | None = None, plan_timeout_s: float | None = None,
    plan_chunk_views: int = DEFAULT_CHUNK_VIEWS,
) -> Job:
    """Create a pending job over the tenant's spaces; 404 for a space that is not theirs, 422 for a cue it
    lacks or a plan over the planning budget (`plan_memory_mb`, `plan_timeout_s`, planned in
    `plan_chunk_views`)."""
    found = {
        s.id: s
        for s in session.scalars(
            select(Space).where(Space.id.in_(body.space_ids), Space.owner == owner)
        ).all()
    }
    missing = [i for i in body.space_ids if i not in found]
    if missing:
        raise not_found("space" if len(missing) == 1 else "spaces", ", ".join(map(str, missing)))
    try:
        if plan_memory_mb is not None:
            check_plan_budget(body.spec, memory_mb=plan_memory_mb, timeout_s=plan_timeout_s,
                              chunk_views=plan_chunk_views)
        job = core_jobs.create_job(
            session, owner=owner, spec=body.spec, spaces=[found[i] for i in body.space_ids]
        )
    except ValueError as e:
        session.rollback()
        raise Invalid(str(e)) from None
    session.commit()
    return job


ACTIONS: dict[str, Callable[[Session, Job], object]] = {
    "cancel": core_jobs.cancel_job,
    "pause": core_jobs.pause_job,
    "resume": core_jobs.resume_job,
    "retry": core_jobs.retry_failed,
}


def apply_action(session: Session, *, owner: str, job_id: int, action: str) -> Job:
    """Run a lifecycle action (cancel, pause, resume, retry) on the tenant's job; 409 if its state forbids
    it."""
    job = get_job(session, owner=owner, job_id=job_id)
    try:
        ACTIONS[action](session, job)
    except core_jobs.JobStateError as e:
        session.rollback()
        raise Conflict(str(e)) from None
    session.commit()
    session.refresh(job)
    return job


def delete_job(session: Session, store: ObjectStore, *, owner: str, job_id: int) -> None:
    """Delete the tenant's job with its outputs (an unfinished job is cancelled first)."""
    job = get_job(session, owner=owner, job_id=job_id)
    core_jobs.delete_job(session, store, job)
    session.commit()
