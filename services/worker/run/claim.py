"""Claiming a task and recording its result: the worker's side of the task state machine.

Claim: queued -> running (worker_id = me, attempts + 1, lease) only while the job is running. A stale or
duplicate message claims nothing; a paused job's task, or one of a job this worker is blocked on, is handed
back to pending so another worker (or the resumed job) takes it. Done: running -> done with size, sha256 and
duration, only WHERE worker_id = me AND state = 'running' (a reaped-and-rerun task wrote identical bytes
anyway). Failure: see services.worker.run.failure_policy. Every step is retried through dropped database
connections (a Postgres restart) for `db_retry_s`, so a blip does not fail work that was done.
"""

from __future__ import annotations

import logging
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, TypeVar

from sqlalchemy import select
from sqlalchemy.exc import DBAPIError, DisconnectionError, InterfaceError, OperationalError
from sqlalchemy.orm import Session

from services.core.db.jobs import hold_for_storage
from services.core.db.models import Job, JobState, Task, TaskState, utcnow
from services.core.db.states import transition
from services.core.db.worker_moves import claim_task, claim_view_tasks, finish_task, finish_tasks, task_state
from services.core.domain.cues import CATALOG, topological_order
from services.core.storage import ObjectInfo
from services.worker.run.failure_policy import HANDBACK_DELAY, count_failure, is_blocked, retry_delay

log = logging.getLogger(__name__)

T = TypeVar("T")

DB_RETRY_S = 60.0  # how long one database step is retried through a connection drop before giving up
ERROR_MAX_CHARS = 4000

CUE_ORDER = {cue: k for k, cue in enumerate(topological_order(CATALOG))}  # a batch runs inputs first
STATUSES = ("done", "skipped", "paused", "blocked", "held", "retry", "failed", "discarded", "lost")


class TransientError(Exception):
    """The runner could not reach the database to claim the task: the message should be retried later."""


@dataclass(frozen=True)
class Outcome:
    """What `TaskRunner.run` did with one task.

    status: done (output stored and recorded) | skipped (stale/duplicate message, or the job is not running,
    or handed back to pending unrun because an input failed in its view batch) | paused / blocked (handed back
    to pending) | held (the object store failed: back to pending, its attempt not counted, and the job paused
    until the store takes writes again) | retry (failed, back to pending after a backoff) | failed (for good)
    | discarded (computed, but the task was no longer ours: reaped or cancelled) | lost (could not record the
    result; the lease runs out and the reaper retries it).
    """

    task_id: int
    status: str
    cue: str | None = None
    job_id: int | None = None
    key: str | None = None
    size: int | None = None
    sha256: str | None = None
    error: str | None = None
    duration_s: float = 0.0
    recycle: bool = False
    # the view's other tasks this worker ran along with this one (a view batch)
    batch: tuple[Outcome, ...] = ()

    def all(self) -> tuple[Outcome, ...]:
        """This outcome and those of its batch."""
        return (self, *self.batch)

    @property
    def labels(self) -> int:
        """Dataset files this task produced (the internal pass set is not a label)."""
        return int(self.status == "done" and self.cue is not None and not CATALOG[self.cue].internal)


@dataclass(frozen=True)
class Claimed:
    """A task this worker holds (state running, worker_id = this worker)."""

    id: int
    job_id: int
    space_id: int
    point: int
    view: int
    cue: str
    attempts: int  # including this attempt


def is_transient_db_error(exc: BaseException) -> bool:
    """Connection-level database errors (server restarted, connection killed, SQLite busy) worth retrying."""
    if isinstance(exc, OperationalError | InterfaceError | DisconnectionError):
        return True
    return isinstance(exc, DBAPIError) and bool(exc.connection_invalidated)


def format_error(exc: BaseException, frames: int = 4) -> str:
    """`Type: message` then the last few traceback frames (what a failed task keeps as its error)."""
    head = f"{type(exc).__name__}: {exc}".strip()
    tail = traceback.extract_tb(exc.__traceback__)[-frames:]
    lines = [head] + [f"  at {Path(f.filename).name}:{f.lineno} in {f.name}" for f in tail]
    text = "\n".join(lines)
    return text if len(text) <= ERROR_MAX_CHARS else text[: ERROR_MAX_CHARS - 3] + "..."


def retry_db(fn: Callable[[], T], what: str, retry_s: float) -> T:
    """Run a database step, retrying it through dropped connections (Postgres restart) for `retry_s`."""
    deadline = time.monotonic() + retry_s
    delay = 0.2
    while True:
        try:
            return fn()
        except Exception as exc:
            if not is_transient_db_error(exc) or time.monotonic() + delay > deadline:
                raise
            log.warning("%s: database error (%s), retrying in %.1f s", what, type(exc).__name__, delay)
            time.sleep(delay)
            delay = min(delay * 2, 5.0)


def split_on_inputs(claimed: list[Claimed], others: tuple[str, ...]) -> tuple[list[Claimed], list[Claimed]]:
    """(tasks that may run in the batch, those an input of which is among `others`, the view's cues left
    elsewhere, directly or through another such task); `claimed` in topological order."""
    missing, runnable, waiting = set(others), [], []
    for c in claimed:
        if missing.intersection(CATALOG[c.cue].inputs):
            waiting.append(c)
            missing.add(c.cue)
        else:
            runnable.append(c)
    return runnable, waiting


class TaskLedger:
    """One worker's claims and records in the database (`worker_id`, e.g. host:pid)."""

    def __init__(
        self, sessionmaker: Callable[[], Session], worker_id: str, lease_s: float, db_retry_s: float
    ) -> None:
        self.sessionmaker = sessionmaker
        self.worker_id = worker_id
        self.lease_s = lease_s
        self.db_retry_s = db_retry_s

    def db(self, fn: Callable[[], T], what: str) -> T:
        """Run a database step with this worker's retry budget."""
        return retry_db(fn, what, self.db_retry_s)

    def claim(self, task_id: int) -> Claimed | Outcome:
        """queued -> running for this worker, or the Outcome saying why not; TransientError when
        unreachable."""
        try:
            return self.db(lambda: self._claim(task_id), f"claim task {task_id}")
        except Exception as exc:
            if is_transient_db_error(exc):
                raise TransientError(f"could not claim task {task_id}: {format_error(exc, 0)}") from exc
            raise

    def _claim(self, task_id: int) -> Claimed | Outcome:
        fast = self._claim_queued(task_id)
        if fast is not None:
            return fast
        # Not claimed in one statement: find out why (stale or duplicate message, paused job, blocked worker,
        # a claim of ours whose reply was lost) and act on it.
        now = utcnow()
        with self.sessionmaker() as s:
            row = s.execute(
                select(Task.job_id, Task.space_id, Task.point_idx, Task.view_idx, Task.cue, Task.state,
                       Task.attempts, Task.worker_id, Job.state.label("job_state"))
                .join(Job, Job.id == Task.job_id)
                .where(Task.id == task_id)
            ).first()
            if row is None:
                return Outcome(task_id, "skipped", error="no such task")

            def claimed(attempts: int) -> Claimed:
                return Claimed(task_id, int(row.job_id), int(row.space_id), int(row.point_idx),
                               int(row.view_idx), str(row.cue), attempts)

            if (
                row.state == TaskState.RUNNING
                and row.worker_id == self.worker_id
                and row.job_state == JobState.RUNNING
            ):
                # Ours already: a claim whose commit reply was lost in a connection drop, retried. This
                # process runs one task at a time, so nothing else here is running it.
                return claimed(int(row.attempts))
            if row.state != TaskState.QUEUED:
                return Outcome(task_id, "skipped", cue=row.cue, job_id=row.job_id,
                               error=f"task is {row.state}, not queued (stale or duplicate message)")
            handed_back = self._hand_back(s, task_id, int(row.job_id), str(row.job_state), now)
            if handed_back is not None:
                return Outcome(task_id, handed_back, cue=row.cue, job_id=row.job_id)
            if row.job_state != JobState.RUNNING:
                return Outcome(
                    task_id, "skipped", cue=row.cue, job_id=row.job_id, error=f"job is {row.job_state}"
                )
            moved = transition(
                s, job_id=row.job_id, task_ids=[task_id], from_state=TaskState.QUEUED,
                to_state=TaskState.RUNNING, worker_id=self.worker_id, attempts=Task.attempts + 1,
                started_at=now, finished_at=None,
                lease_until=now + timedelta(seconds=self.lease_s),
            )
            s.commit()
            if not moved:  # another worker got there between our read and our update
                return Outcome(
                    task_id, "skipped", cue=row.cue, job_id=row.job_id, error="claimed by another worker"
                )
            return claimed(int(row.attempts) + 1)

    def _claim_queued(self, task_id: int) -> Claimed | None:
        """The common case in one statement (one round trip on Postgres): queued -> running for this worker
        while its job runs and the worker is not kept off the job; None when that did not apply."""
        now = utcnow()
        with self.sessionmaker() as s:
            r = claim_task(s, task_id=task_id, worker_id=self.worker_id, now=now,
                           lease_until=now + timedelta(seconds=self.lease_s))
        if r is None:
            return None
        return Claimed(task_id, int(r.job_id), int(r.space_id), int(r.point_idx), int(r.view_idx), str(r.cue),
                       int(r.attempts))  # RETURNING gives the new values: attempts counts this attempt

    def claim_view_rest(self, t: Claimed, *, with_pending: bool = False) -> tuple[list[Claimed], bool]:
        """The view batch: -> running for this worker, in ONE statement, of the rest of `t`'s view (same job,
        space, point, view; not its `passes` task) while the job runs and the worker is not kept off it: the
        queued tasks, and with `with_pending` (t is the view's rendered `passes`, or a cue read from the
        view's pass set) the pending ones too. Every input of those is a cue of the same view, derived from
        the pass set this worker holds. A queued task's
        message, when it comes, finds it running or done and is skipped at the claim; a pending one has none.
        Returns them in topological order of their cues, and whether another task of the view that reads the
        pass set may still run elsewhere (True when nothing was claimed: unknown). ([], True) when the
        database is unreachable (they run one by one). A pending task whose input is left elsewhere (another
        worker runs it and may still fail it) is handed back at once: it runs once that input is done, or
        fails with it (the dispatcher's rule), never beside it."""
        def step() -> tuple[list[Claimed], bool, tuple[str, ...]]:
            now = utcnow()
            with self.sessionmaker() as s:
                rows = claim_view_tasks(
                    s, task_id=t.id, job_id=t.job_id, space_id=t.space_id, point=t.point, view=t.view,
                    worker_id=self.worker_id, now=now, lease_until=now + timedelta(seconds=self.lease_s),
                    with_pending=with_pending,
                )
            claimed = sorted((Claimed(int(r[0]), t.job_id, t.space_id, t.point, t.view, str(r[1]), int(r[3]))
                              for r in rows), key=lambda c: (CUE_ORDER[c.cue], c.id))
            return claimed, not rows or int(rows[0][5]) > 0, tuple(rows[0][6]) if rows else ()

        try:
            claimed, elsewhere, others = self.db(step, f"claim the view batch of task {t.id}")
        except Exception as exc:
            if not is_transient_db_error(exc):
                raise
            log.warning("task %d: view batch not claimed (%s)", t.id, format_error(exc, 0))
            return [], True
        runnable, waiting = split_on_inputs(claimed, others)
        if waiting:
            log.info("view batch of task %d: %s handed back, an input runs elsewhere", t.id,
                     ", ".join(c.cue for c in waiting))
            self.hand_back(waiting, "handed back to pending unrun: an input of its view runs elsewhere")
        return runnable, elsewhere or bool(waiting)

    def hand_back(self, tasks: list[Claimed], why: str) -> list[Outcome]:
        """running -> pending, as before their claim (attempts, no worker, no lease), of batch tasks that did
        not run because an input of theirs failed in the batch: the dispatcher queues them once their inputs
        are done, or fails them with the input. 'lost' when the database stays away (the reaper retries
        them)."""
        return self._to_pending(tasks, "skipped", why, f"hand back {len(tasks)} tasks of a view batch")

    def is_settled(self, task_id: int) -> bool:
        """True when the task is neither queued nor pending (a read, no lock, no transaction on Postgres): a
        message for a task this worker already ran in a view batch needs no claim attempt."""
        def step() -> bool:
            with self.sessionmaker() as s:
                state = task_state(s, task_id)
            return state is not None and state not in (TaskState.QUEUED, TaskState.PENDING)

        try:
            return self.db(step, f"read task {task_id}")
        except Exception as exc:
            if is_transient_db_error(exc):
                return False  # the claim will tell (TransientError)
            raise

    def record_done_many(self, done: list[tuple[Claimed, str, ObjectInfo, float]]) -> list[Outcome]:
        """running -> done, in ONE statement, of a batch's finished tasks (task, key, stored object, seconds),
        each with its own key, size, sha256 and duration; a task no longer ours is 'discarded', and all are
        'lost' when the database stays away (their leases run out and the reaper retries them)."""
        if len(done) == 1:
            return [self.record_done(*done[0])]
        ids = [t.id for t, *_ in done]
        results = [(t.id, key, int(info.size), info.sha256, float(d)) for t, key, info, d in done]

        def step() -> set[int]:
            with self.sessionmaker() as s:
                return finish_tasks(s, worker_id=self.worker_id, results=results,
                                    now=utcnow())

        try:
            ours = self.db(step, f"record {len(done)} tasks of a view batch done")
        except Exception as exc:
            log.error("tasks %s: outputs stored but not recorded (%s); the reaper will retry them", ids,
                      format_error(exc, 0))
            return [Outcome(t.id, "lost", t.cue, t.job_id, key, info.size, info.sha256, format_error(exc), d)
                    for t, key, info, d in done]
        return [Outcome(t.id, "done" if t.id in ours else "discarded", t.cue, t.job_id, key, int(info.size),
                        info.sha256, None, d) for t, key, info, d in done]

    def _hand_back(self, s: Session, task_id: int, job_id: int, job_state: str, now: datetime) -> str | None:
        """queued -> pending for a paused job ('paused') or a job this worker is blocked on ('blocked')."""
        if job_state == JobState.PAUSED:
            transition(
                s, job_id=job_id, task_ids=[task_id], from_state=TaskState.QUEUED, to_state=TaskState.PENDING,
                queued_at=None,
            )
            s.commit()
            return "paused"
        if job_state == JobState.RUNNING and is_blocked(s, self.worker_id, job_id, now):
            transition(
                s, job_id=job_id, task_ids=[task_id], from_state=TaskState.QUEUED, to_state=TaskState.PENDING,
                queued_at=None, not_before=now + HANDBACK_DELAY,
            )
            s.commit()
            return "blocked"
        return None

    def _move_mine(self, s: Session, t: Claimed, to_state: TaskState, **values: object) -> bool:
        """running -> to_state for a task still held by this worker; counters follow (states.transition)."""
        return bool(
            transition(
                s, job_id=t.job_id, task_ids=[t.id], from_state=TaskState.RUNNING, to_state=to_state,
                where=[Task.worker_id == self.worker_id],
                **values,
            )
        )

    def record_done(self, t: Claimed, key: str, info: ObjectInfo, duration: float) -> Outcome:
        """running -> done with the stored object's size and sha256; 'lost' when the database stays away."""
        def step() -> bool:
            with self.sessionmaker() as s:
                return finish_task(
                    s, task_id=t.id, worker_id=self.worker_id, key=key, size=int(info.size),
                    sha256=info.sha256, duration_s=float(duration), now=utcnow(),
                )

        try:
            ok = self.db(step, f"record task {t.id} done")
        except Exception as exc:
            log.error("task %d: output stored at %s but not recorded (%s); the reaper will retry it",
                      t.id, key, format_error(exc, 0))
            return Outcome(
                t.id, "lost", t.cue, t.job_id, key, info.size, info.sha256, format_error(exc), duration
            )
        status = "done" if ok else "discarded"
        if not ok:
            log.info("task %d finished but is no longer ours (reaped or cancelled); result discarded", t.id)
        return Outcome(t.id, status, t.cue, t.job_id, key, int(info.size), info.sha256, None, duration)

    def hold_for_storage(self, tasks: list[Claimed], problem: BaseException) -> list[Outcome]:
        """running -> pending of tasks whose outputs the store would not take (`problem`: a
        StorageUnavailable), their attempt not counted and no failure counted against this worker (the store
        failed, not the task nor the worker), and their job paused for its store
        (services.core.db.jobs.hold_for_storage): no attempt budget burnt and no worker kept off the job for a
        full disk. 'lost' when the database stays away."""
        error = format_error(problem)

        def pause_job(s: Session) -> None:
            # the job's row first, as cancel and delete lock it: the same order, no deadlock with them
            if hold_for_storage(s, tasks[0].job_id, str(problem)):
                log.warning("job %d paused: %s", tasks[0].job_id, problem)

        return self._to_pending(tasks, "held", error, f"hand back {len(tasks)} tasks the store did not take",
                                before=pause_job, not_before=None, error=error)

    def _to_pending(self, tasks: list[Claimed], status: str, why: str, what: str,
                    before: Callable[[Session], None] | None = None, **columns: Any) -> list[Outcome]:
        """running -> pending of this worker's `tasks`, their attempt not counted, in one transaction
        (`before` runs first in it); each Outcome is `status`, or 'discarded' for a task no longer this
        worker's, or 'lost' when the database stays away (the reaper retries them)."""
        def step() -> set[int]:
            with self.sessionmaker() as s:
                if before is not None:
                    before(s)
                moved = transition(s, job_id=tasks[0].job_id, task_ids=[t.id for t in tasks],
                                   from_state=TaskState.RUNNING, to_state=TaskState.PENDING,
                                   where=[Task.worker_id == self.worker_id], worker_id=None, lease_until=None,
                                   started_at=None, queued_at=None, attempts=Task.attempts - 1, **columns)
                s.commit()
                return {tid for tid, _ in moved}

        try:
            ours = self.db(step, what)
        except Exception as exc:
            log.error("tasks %s: not handed back (%s); the reaper will retry them", [t.id for t in tasks],
                      format_error(exc, 0))
            return [Outcome(t.id, "lost", t.cue, t.job_id, error=format_error(exc)) for t in tasks]
        return [
            Outcome(t.id, status if t.id in ours else "discarded", t.cue, t.job_id, error=why) for t in tasks
        ]

    def record_failure(self, t: Claimed, exc: BaseException, duration: float, max_attempts: int) -> Outcome:
        """running -> pending after a backoff while attempts remain, else failed; counts the worker's
        failure."""
        error = format_error(exc)
        log.warning("task %d (%s, job %d) failed on attempt %d: %s", t.id, t.cue, t.job_id, t.attempts,
                    error.splitlines()[0])

        def step() -> str:
            now = utcnow()
            with self.sessionmaker() as s:
                if t.attempts < max_attempts:
                    status = "retry"
                    ok = self._move_mine(
                        s, t, TaskState.PENDING, error=error, lease_until=None, queued_at=None,
                        worker_id=None,
                        not_before=now + retry_delay(t.attempts),
                    )
                else:
                    status = "failed"
                    ok = self._move_mine(
                        s, t, TaskState.FAILED, error=error, lease_until=None, finished_at=now,
                        duration_s=float(duration),
                    )
                count_failure(s, self.worker_id, t.job_id, now)
                s.commit()
                return status if ok else "discarded"

        try:
            status = self.db(step, f"record failure of task {t.id}")
        except Exception as db_exc:
            log.error("task %d: could not record its failure (%s); the reaper will retry it", t.id,
                      format_error(db_exc, 0))
            status = "lost"
        return Outcome(t.id, status, t.cue, t.job_id, error=error, duration_s=duration)
