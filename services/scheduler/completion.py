"""Completion: finish running jobs whose counters say nothing is pending, queued or running.

For each such job: write manifest.jsonl and job.json (services.core.db.manifest), delete the internal pass
cache, and set the job done, or failed with a summary when any task failed. Reads counters only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from sqlalchemy import exists, func, select
from sqlalchemy.orm import Session

from services.core.db.counters import job_progress
from services.core.db.jobs import hold_for_storage, root_key
from services.core.db.manifest import write_job_files
from services.core.db.models import TASK_ACTIVE_STATES, Job, JobCounter, JobState, Task, TaskState, utcnow
from services.core.db.states import set_job_state
from services.core.storage import ObjectStore, storage_outage

log = logging.getLogger(__name__)

PASS_CACHE_PREFIX = "_cache/"  # keys.passes_key puts every pass set under it


@dataclass(frozen=True)
class Finished:
    """A job that completion finished."""

    job_id: int
    state: str
    error: str | None


def finished_job_ids(session: Session) -> list[int]:
    """Running jobs with tasks, none of which is pending, queued or running (counters only)."""
    c = JobCounter
    # counts are sums over the counter shards: some shard of an active state may be negative, another positive
    active = exists(
        select(c.cue).where(c.job_id == Job.id, c.state.in_(TASK_ACTIVE_STATES))
        .group_by(c.cue, c.state).having(func.sum(c.n) > 0)
    )
    rows = session.execute(
        select(Job.id).where(Job.state == JobState.RUNNING, Job.total_tasks > 0, ~active).order_by(Job.id)
    ).all()
    return [int(r[0]) for r in rows]


def failure_summary(session: Session, job: Job, progress: dict[str, dict[str, int]]) -> str | None:
    """'N of M tasks failed (cue: n, ...); first: <error>' or None when nothing failed."""
    failed = {cue: s[TaskState.FAILED] for cue, s in progress.items() if s.get(TaskState.FAILED)}
    if not failed:
        return None
    total = sum(sum(s.values()) for s in progress.values())
    first = session.execute(
        select(Task.id, Task.cue, Task.point_idx, Task.view_idx, Task.error)
        .where(Task.job_id == job.id, Task.state == TaskState.FAILED)
        .order_by(Task.id)
        .limit(1)
    ).first()
    per_cue = ", ".join(f"{cue}: {n}" for cue, n in sorted(failed.items()))
    msg = f"{sum(failed.values())} of {total} tasks failed ({per_cue})"
    if first is not None:
        err = (first.error or "no error recorded").strip().splitlines()
        head = err[0] if err else ""
        tail = err[-1] if len(err) > 1 else ""
        msg += (
            f"; first: task {first.id} ({first.cue}, point {first.point_idx}, view {first.view_idx}): {head}"
        )
        if tail and tail != head:
            msg += f" ... {tail}"
    return msg


def complete_job(session: Session, store: ObjectStore, job_id: int) -> Finished | None:
    """Finish one job if it is still running with no active task; commits. None when it was not finished."""
    stmt = select(Job).where(Job.id == job_id).execution_options(populate_existing=True)
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update(skip_locked=True)  # another scheduler finishing it: leave it
    job = session.scalars(stmt).first()
    if job is None or job.state != JobState.RUNNING:
        session.rollback()
        return None
    progress = job_progress(session, job.id)
    if any(s.get(st) for s in progress.values() for st in TASK_ACTIVE_STATES):
        session.rollback()
        return None
    error = failure_summary(session, job, progress)
    set_job_state(job, JobState.FAILED if error else JobState.DONE, error=error, finished_at=utcnow())
    session.flush()
    try:
        write_job_files(session, store, job)
        store.delete_prefix(root_key(job, PASS_CACHE_PREFIX))
    except Exception:
        session.rollback()  # the job stays running; the next pass tries again
        raise
    session.commit()
    log.info("job %d finished: %s%s", job.id, job.state, f" ({error})" if error else "")
    return Finished(job.id, job.state, error)


def complete_once(session: Session, store: ObjectStore) -> list[Finished]:
    """Finish every running job that has nothing left to do; a job whose files fail to write is retried later
    (held for its store when the store is full or down)."""
    done: list[Finished] = []
    for job_id in finished_job_ids(session):
        session.rollback()  # end the read transaction before taking the job's lock
        try:
            fin = complete_job(session, store, job_id)
        except Exception as exc:
            outage = storage_outage(exc)
            if outage is None:
                log.exception("finishing job %d failed; will retry", job_id)
                continue
            # its files cannot be written for now: held like its tasks, so the job says why (StoreWatch
            # resumes it)
            log.warning("finishing job %d waits for the store: %s", job_id, outage)
            hold_for_storage(session, job_id, str(outage))
            session.commit()
            continue
        if fin is not None:
            done.append(fin)
    return done
