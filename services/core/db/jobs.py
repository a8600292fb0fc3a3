"""Job lifecycle operations shared by the API, the scheduler and `generate` (execution contract).

Job states: pending -> planning -> running -> done | failed; running <-> paused; any non-final -> cancelled.
Every state change goes through services.core.db.states (the allowed transitions, and the task counters in the
caller's transaction). No function here commits: the caller does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from sqlalchemy import case, delete, select
from sqlalchemy.orm import Session

from services.core.db.compacted import expand_missing
from services.core.db.frame_choice import check_frame_decided
from services.core.db.models import (
    JOB_TERMINAL_STATES,
    Camera,
    CompactedDuration,
    Job,
    JobCounter,
    JobSpace,
    JobState,
    Point,
    Space,
    Task,
    TaskState,
    View,
    ViewOutput,
    WorkerBlock,
    utcnow,
)
from services.core.db.plan_claims import PLANNING_LEASE_S as PLANNING_LEASE_S  # re-exported: their old home
from services.core.db.plan_claims import claim_pending_jobs as claim_pending_jobs
from services.core.db.states import set_job_state, transition
from services.core.domain.cues import CATALOG, closure
from services.core.domain.errors import Conflict
from services.core.domain.jobspec import JobSpec, cues_for_space
from services.core.storage import ObjectStore

RETRY_BACKOFF_BASE_S = 5.0
RETRY_BACKOFF_CAP_S = 300.0


class JobStateError(Conflict, ValueError):
    """An operation that the job's current state does not allow (e.g. resuming a finished job)."""


def retry_backoff_s(attempts: int) -> float:
    """Seconds to wait before retrying a task that has failed `attempts` times (exponential, capped)."""
    return float(min(RETRY_BACKOFF_CAP_S, RETRY_BACKOFF_BASE_S * 2 ** max(0, attempts - 1)))


def job_spec(job: Job) -> JobSpec:
    """The job's JobSpec, parsed from its stored JSON."""
    return JobSpec.model_validate(job.spec)


def job_root(job: Job) -> str:
    """The job's output root without a trailing '/' ('' for the embedded layout)."""
    return (job.output_root or "").strip("/")


def root_key(job: Job, key: str) -> str:
    """`key` (relative to the job's output root) as a key of the object store."""
    root = job_root(job)
    return f"{root}/{key}" if root else key


def create_job(
    session: Session,
    *,
    owner: str,
    spec: JobSpec,
    spaces: Sequence[Space],
    output_root: str | None = None,
) -> Job:
    """Create a pending job over `spaces` (in order) with its per-space cue lists; flushes, does not commit.

    Raises ValueError when there is no space, a space is listed twice or two share a name (their outputs
    would collide), a space belongs to another owner, or a space cannot give a requested cue (naming the
    cue and the reason). `output_root` defaults to `jobs/<id>`.
    """
    if not spaces:
        raise ValueError("a job needs at least one space")
    seen_ids: set[int] = set()
    seen_names: set[str] = set()
    per_space: list[list[str]] = []
    for space in spaces:
        if space.id in seen_ids or space.name in seen_names:
            raise ValueError(
                f"space {space.name!r} is listed twice (space names must be distinct within a job)"
            )
        seen_ids.add(space.id)
        seen_names.add(space.name)
        if space.owner != owner:
            raise ValueError(f"space {space.name!r} (id {space.id}) does not belong to {owner!r}")
        check_frame_decided(spec, space)
        try:
            per_space.append(cues_for_space(spec, has_semantics=bool(space.has_semantics)))
        except ValueError as e:
            raise ValueError(f"space {space.name!r}: {e}") from None
    job = Job(
        owner=owner,
        name=spec.name,
        spec=spec.model_dump(mode="json"),
        state=JobState.PENDING,
        priority=spec.priority,
        output_root=(output_root or "").strip("/"),
        total_tasks=0,
    )
    session.add(job)
    session.flush()
    if output_root is None:
        job.output_root = f"jobs/{job.id}"
    for pos, (space, cues) in enumerate(zip(spaces, per_space, strict=True)):
        session.add(JobSpace(job_id=job.id, space_id=space.id, position=pos, cues=cues))
    session.flush()
    return job


def job_spaces(session: Session, job_id: int) -> list[tuple[JobSpace, Space]]:
    """The job's spaces in submission order, each with its JobSpace row."""
    rows = session.execute(
        select(JobSpace, Space)
        .join(Space, Space.id == JobSpace.space_id)
        .where(JobSpace.job_id == job_id)
        .order_by(JobSpace.position, JobSpace.space_id)
    ).all()
    return [(job_space, space) for job_space, space in rows]


def job_cues(session: Session, job_id: int) -> list[str]:
    """Output cues requested on any space of the job, in catalog order."""
    names: set[str] = set()
    for job_space, _space in job_spaces(session, job_id):
        names.update(job_space.cues)
    return [c for c in closure(names) if c in names]


def _lock_job(session: Session, job: Job) -> Job:
    # Re-read the row under a lock so racing operations (cancel vs. complete) serialise on Postgres. NO KEY: a
    # planner's open transaction holds KEY SHARE on the job row (its inserted rows reference it), and a cancel
    # must not wait for the whole planning to commit.
    stmt = select(Job).where(Job.id == job.id).execution_options(populate_existing=True)
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update(key_share=True)  # FOR NO KEY UPDATE
    locked = session.scalars(stmt).one()
    return locked


def _lock_job_key(session: Session, job_id: int) -> Job | None:
    """The job re-read under FOR UPDATE (the lock a delete of the row needs), or None once it is gone. Taken
    before any other row of the job is touched: it waits for a planner's open chunk transaction (KEY SHARE on
    the row) to end, while that planner's own look at the job (FOR SHARE) does not wait for it."""
    stmt = select(Job).where(Job.id == job_id).execution_options(populate_existing=True)
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update()
    return session.scalars(stmt).one_or_none()


def cancel_job(session: Session, job: Job) -> int:
    """Cancel a non-final job: job -> cancelled, its pending and queued tasks -> cancelled at once.

    Running tasks finish (their result is kept) or are discarded by the worker. Returns the number of
    tasks cancelled. Raises JobStateError for a job that is already done, failed or cancelled.

    A job still planning changes its own row only: its planner may be inside a chunk's transaction, holding
    task and counter rows while it waits to re-read the job (which this lock makes it do), so touching those
    rows here could deadlock. The planner sees the cancel and stops; whoever stops it removes the chunks
    already written (services.scheduler.persist.drop_cancelled_plan), as a delete does.
    """
    job = _lock_job(session, job)
    if job.state in JOB_TERMINAL_STATES:
        raise JobStateError(f"job {job.id} is {job.state}; only unfinished jobs can be cancelled")
    now = utcnow()
    planning = job.state == JobState.PLANNING
    set_job_state(job, JobState.CANCELLED, finished_at=now)
    session.flush()
    if planning:
        return 0
    # pending first, then queued: a task a dispatcher moves pending -> queued meanwhile is caught second.
    n = len(transition(session, job_id=job.id, from_state=TaskState.PENDING, to_state=TaskState.CANCELLED,
                       finished_at=now))
    n += len(transition(session, job_id=job.id, from_state=TaskState.QUEUED, to_state=TaskState.CANCELLED,
                        finished_at=now))
    return n


def pause_job(session: Session, job: Job) -> None:
    """Pause a running job: nothing more is dispatched; queued tasks go back to pending when received. A job
    the service paused for its store becomes its owner's pause: it stays paused when the store comes back."""
    job = _switch(session, job, JobState.RUNNING, JobState.PAUSED, "paused")
    job.paused_by = None


def resume_job(session: Session, job: Job) -> None:
    """Resume a paused job (one held for its store too: if the store still fails, the next task holds it
    again)."""
    job = _switch(session, job, JobState.PAUSED, JobState.RUNNING, "resumed")
    if job.paused_by is not None:
        job.paused_by = job.error = None


# A job held for its store: paused by the service, not its owner, and resumed by the scheduler (StoreWatch).
PAUSED_BY_STORAGE = "storage"
HELD_SUFFIX = "; the job waits and resumes on its own once the store takes writes again"


def hold_for_storage(session: Session, job_id: int, problem: str) -> bool:
    """running -> paused because the object store failed (`problem`: StorageUnavailable's message, kept as the
    job's error, so the job read and the dashboard say it); a job already held takes the newer problem. True
    when this call paused it. Its tasks wait in pending, their attempts not counted."""
    job = session.get(Job, job_id)
    if job is None:
        return False
    job = _lock_job(session, job)
    if job.state == JobState.RUNNING:
        set_job_state(job, JobState.PAUSED, paused_by=PAUSED_BY_STORAGE, error=problem + HELD_SUFFIX)
        session.flush()
        return True
    if job.state == JobState.PAUSED and job.paused_by == PAUSED_BY_STORAGE:
        job.error = problem + HELD_SUFFIX
    return False


def storage_held_jobs(session: Session) -> list[tuple[int, str | None]]:
    """(id, error) of the jobs held for their store, oldest first."""
    rows = session.execute(select(Job.id, Job.error).where(
        Job.state == JobState.PAUSED, Job.paused_by == PAUSED_BY_STORAGE).order_by(Job.id))
    return [(int(i), e) for i, e in rows]


def release_storage_holds(session: Session, job_ids: Sequence[int]) -> list[int]:
    """paused -> running for those of `job_ids` still held for their store (not since paused or cancelled by
    their owner); returns their ids."""
    released = []
    for job_id in job_ids:
        job = session.get(Job, job_id)
        if job is None:
            continue
        job = _lock_job(session, job)
        if job.state == JobState.PAUSED and job.paused_by == PAUSED_BY_STORAGE:
            set_job_state(job, JobState.RUNNING, paused_by=None, error=None)
            released.append(job_id)
    session.flush()
    return released


def _switch(session: Session, job: Job, src: JobState, dst: JobState, done: str) -> Job:
    # Idempotent: a job already in `dst` is left alone; any state but `src` is refused. Returns the locked
    # row.
    job = _lock_job(session, job)
    if job.state == dst:
        return job
    if job.state != src:
        raise JobStateError(f"job {job.id} is {job.state}; only a {src} job can be {done}")
    set_job_state(job, dst)
    session.flush()
    return job


def retry_failed(session: Session, job: Job) -> int:
    """Put the job's failed tasks back to pending with attempts reset; a failed/done job runs again.

    Returns the number of tasks retried. Raises JobStateError for a cancelled job or one not planned yet.
    """
    job = _lock_job(session, job)
    if job.state in (JobState.CANCELLED, JobState.PENDING, JobState.PLANNING):
        raise JobStateError(f"job {job.id} is {job.state}; failed tasks can only be retried once it has run")
    n = len(transition(
        session, job_id=job.id, from_state=TaskState.FAILED, to_state=TaskState.PENDING,
        attempts=0, error=None, not_before=None, worker_id=None, lease_until=None, finished_at=None,
    ))
    # A worker blocked on this job for repeated failures gets another chance after an explicit retry.
    session.execute(delete(WorkerBlock).where(WorkerBlock.job_id == job.id))
    if n and job.state in (JobState.DONE, JobState.FAILED):
        set_job_state(job, JobState.RUNNING, error=None, finished_at=None)
    session.flush()
    return n


def delete_job(session: Session, store: ObjectStore, job: Job) -> int:
    """Delete a job: its outputs in the store, then its rows (tasks, plan, counters); returns objects deleted.

    An unfinished job is cancelled first, in a transaction of its own (committed here): a planner then stops
    at its next look at the job, and the delete waits only for the planner's open chunk, never the reverse
    (one transaction that both cancelled and deleted deadlocked with the planner's chunk inserts). With an
    empty output root (embedded layout) only the job's own files are removed, never the rest of the folder.
    """
    job = _lock_job(session, job)
    if job.state not in JOB_TERMINAL_STATES:
        cancel_job(session, job)
        session.commit()
    locked = _lock_job_key(session, job.id)
    if locked is None:  # deleted meanwhile by another request
        return 0
    job = locked
    deleted = 0
    root = job_root(job)
    if root:
        deleted += store.delete_prefix(root + "/")
    else:
        spec = job_spec(job)
        for _job_space, space in job_spaces(session, job.id):
            for cue in closure(_job_space.cues):
                deleted += store.delete_prefix(f"{cue}/{spec.name}/{space.name}/")
        for prefix in ("_plan/", "_cache/"):
            deleted += store.delete_prefix(prefix)
        for key in ("manifest.jsonl", "job.json"):
            deleted += int(store.delete(key))
    for model in (
        Task, ViewOutput, CompactedDuration, View, Point, Camera, JobCounter, JobSpace, WorkerBlock,
    ):
        session.execute(delete(model).where(model.job_id == job.id))
    session.execute(delete(Job).where(Job.id == job.id))
    session.expunge(job)
    session.flush()
    return deleted


# ---------------------------------------------------------------------------------------------- resume


@dataclass
class Reopened:
    """What reopening a job of an earlier run did."""

    requeued: int = 0  # interrupted tasks put back to pending
    redo: int = 0  # done tasks whose file was missing
    retried: int = 0  # failed tasks given another chance


def requeue_inflight(session: Session, job_id: int) -> int:
    """Queued and running tasks of the job back to pending, their attempt not counted (the run was stopped,
    the task did not fail); returns how many moved. (CASE, not two-argument max(): Postgres has no such
    max.)"""
    n = len(
        transition(
            session, job_id=job_id, from_state=TaskState.RUNNING, to_state=TaskState.PENDING,
            attempts=case((Task.attempts > 0, Task.attempts - 1), else_=0), worker_id=None, lease_until=None,
            queued_at=None, not_before=None,
        )
    )
    n += len(transition(session, job_id=job_id, from_state=TaskState.QUEUED, to_state=TaskState.PENDING,
                        queued_at=None))
    return n


def reopen_job(session: Session, store: ObjectStore, job: Job) -> Reopened:
    """Make a job of an earlier run resumable: in-flight tasks back to pending, missing outputs made again,
    failed tasks retried. A job interrupted while planning plans again from scratch."""
    done = Reopened()
    if job.state == JobState.PLANNING:
        set_job_state(job, JobState.PENDING, planner=None, planner_lease_until=None)
        session.flush()
        return done
    if job.state == JobState.PENDING:
        return done
    if job.state == JobState.PAUSED:  # a hold for the store ends too: the tasks show if it still fails
        set_job_state(job, JobState.RUNNING, **({"paused_by": None, "error": None} if job.paused_by else {}))
    done.requeued = requeue_inflight(session, job.id)
    # Done outputs whose file is gone are made again (the internal pass cache is rebuilt on demand); a
    # compacted view with such an output is put back as task rows first.
    expand_missing(session, job, store.exists)
    internal = [n for n, c in CATALOG.items() if c.internal]
    missing = [
        tid for tid, key in session.execute(
            select(Task.id, Task.output_key).where(
                Task.job_id == job.id, Task.state == TaskState.DONE, Task.cue.not_in(internal)
            )
        )
        if not key or not store.exists(key)
    ]
    done.redo = len(transition(
        session, job_id=job.id, task_ids=missing, from_state=TaskState.DONE, to_state=TaskState.PENDING,
        attempts=0, error=None, output_key=None, size=None, sha256=None, finished_at=None, not_before=None,
    ))
    if job.state in (JobState.DONE, JobState.FAILED, JobState.RUNNING):
        done.retried = retry_failed(session, job)
    if done.redo and job.state in (JobState.DONE, JobState.FAILED):
        set_job_state(job, JobState.RUNNING, error=None, finished_at=None)
    session.flush()
    return done
