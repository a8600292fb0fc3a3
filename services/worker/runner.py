"""TaskRunner: run one task of the execution contract (DESIGN.md section 6).

    runner = TaskRunner(sessionmaker, store, settings, worker_id)
    outcome = runner.run(task_id)

1. Claim: queued -> running (worker_id = me, attempts + 1, lease) only while the job is running. A stale or
   duplicate message claims nothing; a paused job's task, or one of a job this worker is blocked on, is handed
   back to pending so another worker (or the resumed job) takes it.
2. Load the job spec, the space (kept loaded between tasks: SpaceCache) and the plan JSON (cached per process).
3. Compute: the `passes` task renders the view once and stores its pass set (.npz) in the object store's pass
   cache; every other cue is derived from that pass set, read from this process's memory LRU or the store
   (and rendered again only if the cache is gone, e.g. after a resume of a finished job).
4. Write the object atomically to its deterministic key, then running -> done with size, sha256 and duration,
   only WHERE worker_id = me AND state = 'running' (a reaped-and-rerun task wrote identical bytes anyway).
5. Failure: running -> pending after a backoff while attempts < spec.max_attempts, else failed with the error
   (type, message, traceback tail). Three failures of this worker on a job block it there for ten minutes.

Bytes, not files, flow through here; all geometry is in the plan (world metres, OpenCV camera axes).
"""

from __future__ import annotations

import json
import logging
import os
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import timedelta
from pathlib import Path
from typing import Any, TypeVar

from sqlalchemy import or_, select
from sqlalchemy.exc import DBAPIError, DisconnectionError, InterfaceError, OperationalError
from sqlalchemy.orm import Session

from services.core.cues import CATALOG, closure
from services.core.jobs import job_root, retry_backoff_s
from services.core.jobspec import JobSpec
from services.core.keys import output_key, passes_key
from services.core.models import Job, JobState, Space, Task, TaskState, WorkerBlock, utcnow
from services.core.plan import SpacePlan, plan_from_json
from services.core.settings import Settings
from services.core.states import claim_task, finish_task, transition
from services.core.storage import ObjectStore

log = logging.getLogger(__name__)

T = TypeVar("T")

BLOCK_AFTER_FAILURES = 3  # failures of one worker on one job before it is kept off that job
BLOCK_FOR = timedelta(minutes=10)
HANDBACK_DELAY = timedelta(seconds=1)  # a blocked worker's hand-back waits a little, so others get it first
DB_RETRY_S = 60.0  # how long one database step is retried through a connection drop before giving up
PLAN_CACHE_SIZE = 4  # (job, space) plans kept in memory
# Views (pass set + memoised intermediates) kept in memory, least recently used first out, while they hold more than
# this fraction of worker_max_memory_mb (and always the last VIEW_CACHE_MIN): a job's renders are dispatched ahead
# of its derived cues, so a worker meets a view's cues after rendering many other views; each view it dropped
# meant reading its pass set back and recomputing its intermediates (3x per view on a room, ~0.1 CPU-s a view).
VIEW_CACHE_MEMORY_FRACTION = 0.25
VIEW_CACHE_MIN = 4
ERROR_MAX_CHARS = 4000

STATUSES = ("done", "skipped", "paused", "blocked", "retry", "failed", "discarded", "lost")


class TransientError(Exception):
    """The runner could not reach the database to claim the task: the message should be retried later."""


@dataclass(frozen=True)
class Outcome:
    """What `TaskRunner.run` did with one task.

    status: done (output stored and recorded) | skipped (stale/duplicate message, or the job is not running) |
    paused / blocked (handed back to pending) | retry (failed, back to pending after a backoff) | failed (for
    good) | discarded (computed, but the task was no longer ours: reaped or cancelled) | lost (could not record
    the result; the lease runs out and the reaper retries it).
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

    @property
    def labels(self) -> int:
        """Dataset files this task produced (the internal pass set is not a label)."""
        return int(self.status == "done" and self.cue is not None and not CATALOG[self.cue].internal)


@dataclass(frozen=True)
class _Claimed:
    id: int
    job_id: int
    space_id: int
    point: int
    view: int
    cue: str
    attempts: int  # including this attempt


@dataclass(frozen=True)
class _JobInfo:
    id: int
    spec: JobSpec
    root: str  # output root, '' for the embedded layout
    component: str


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


def _needs_passes(cue: str) -> bool:
    return "passes" in closure([cue])


class TaskRunner:
    """Runs tasks for one worker process (`worker_id`, e.g. host:pid); not thread-safe: one task at a time."""

    def __init__(
        self,
        sessionmaker: Callable[[], Session],
        store: ObjectStore,
        settings: Settings,
        worker_id: str,
        *,
        heartbeat: Any = None,
        cache_dir: str | Path | None = None,
        render_threads: int | None = None,
        render_device: str | None = None,
        db_retry_s: float = DB_RETRY_S,
    ) -> None:
        from services.worker.space_cache import SpaceCache

        self.sessionmaker = sessionmaker
        self.store = store
        self.settings = settings
        self.worker_id = worker_id
        self.heartbeat = heartbeat
        self.cache_dir = Path(cache_dir) if cache_dir is not None else settings.data_dir / "cache" / "spaces"
        self.render_threads = render_threads if render_threads is not None else settings.render_threads
        self.render_device = render_device or settings.render_device
        self.db_retry_s = db_retry_s
        self.space_cache = SpaceCache()
        self._jobs: dict[int, _JobInfo] = {}
        self._spaces: dict[int, Space] = {}
        self._plans: OrderedDict[tuple[int, int], SpacePlan] = OrderedDict()
        self._views: OrderedDict[tuple[int, int, int, int], Any] = OrderedDict()  # -> ViewContext with passes
        self.tasks_run = 0
        self.renders = 0  # pass sets rendered by this process (one per view, unless a cache was lost)

    # ------------------------------------------------------------------------------------------ public

    def run(self, task_id: int) -> Outcome:
        """Claim and run one task; never raises for task failures (they are recorded), only TransientError."""
        t0 = time.perf_counter()
        try:
            claimed = self._db(lambda: self._claim(task_id), f"claim task {task_id}")
        except Exception as exc:
            if is_transient_db_error(exc):
                raise TransientError(f"could not claim task {task_id}: {format_error(exc, 0)}") from exc
            raise
        if isinstance(claimed, Outcome):
            return claimed
        self.tasks_run += 1
        if self.heartbeat is not None:
            self.heartbeat.set_current(claimed.id)
        try:
            try:
                key, info = self._execute(claimed)
            except Exception as exc:
                outcome = self._record_failure(claimed, exc, time.perf_counter() - t0)
            else:
                outcome = self._record_done(claimed, key, info, time.perf_counter() - t0)
        finally:
            if self.heartbeat is not None:
                self.heartbeat.set_current(None)
        if self.heartbeat is not None and outcome.status in ("done", "retry", "failed", "discarded"):
            self.heartbeat.record_done(claimed.cue, outcome.labels)
        return replace(outcome, recycle=self.should_recycle())

    def should_recycle(self) -> bool:
        """True when this process should exit after the task: RSS above worker_max_memory_mb or too many tasks."""
        from services.worker.space_cache import should_recycle

        return self.tasks_run >= self.settings.worker_max_tasks or should_recycle(self.settings.worker_max_memory_mb)

    def close(self) -> None:
        """Free the loaded space and cached views."""
        self._views.clear()
        self.space_cache.clear()

    # ------------------------------------------------------------------------------------------ database

    def _db(self, fn: Callable[[], T], what: str) -> T:
        """Run a database step, retrying it through dropped connections (Postgres restart) for db_retry_s."""
        deadline = time.monotonic() + self.db_retry_s
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

    def _claim(self, task_id: int) -> _Claimed | Outcome:
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

            def claimed(attempts: int) -> _Claimed:
                return _Claimed(task_id, int(row.job_id), int(row.space_id), int(row.point_idx),
                                int(row.view_idx), str(row.cue), attempts)

            if row.state == TaskState.RUNNING and row.worker_id == self.worker_id and row.job_state == JobState.RUNNING:
                # Ours already: a claim whose commit reply was lost in a connection drop, retried. This process
                # runs one task at a time, so nothing else here is running it.
                return claimed(int(row.attempts))
            if row.state != TaskState.QUEUED:
                return Outcome(task_id, "skipped", cue=row.cue, job_id=row.job_id,
                               error=f"task is {row.state}, not queued (stale or duplicate message)")
            if row.job_state == JobState.PAUSED:
                transition(s, job_id=row.job_id, task_ids=[task_id], from_state=TaskState.QUEUED, to_state=TaskState.PENDING,
                           queued_at=None)
                s.commit()
                return Outcome(task_id, "paused", cue=row.cue, job_id=row.job_id)
            if row.job_state != JobState.RUNNING:
                return Outcome(task_id, "skipped", cue=row.cue, job_id=row.job_id, error=f"job is {row.job_state}")
            if self._blocked(s, int(row.job_id), now):
                transition(s, job_id=row.job_id, task_ids=[task_id], from_state=TaskState.QUEUED, to_state=TaskState.PENDING,
                           queued_at=None, not_before=now + HANDBACK_DELAY)
                s.commit()
                return Outcome(task_id, "blocked", cue=row.cue, job_id=row.job_id)
            moved = transition(
                s, job_id=row.job_id, task_ids=[task_id], from_state=TaskState.QUEUED, to_state=TaskState.RUNNING,
                worker_id=self.worker_id, attempts=Task.attempts + 1, started_at=now, finished_at=None,
                lease_until=now + timedelta(seconds=self.settings.lease_s),
            )
            s.commit()
            if not moved:  # another worker got there between our read and our update
                return Outcome(task_id, "skipped", cue=row.cue, job_id=row.job_id, error="claimed by another worker")
            return claimed(int(row.attempts) + 1)

    def _claim_queued(self, task_id: int) -> _Claimed | None:
        """The common case in one statement (one round trip on Postgres): queued -> running for this worker while
        its job runs and the worker is not kept off the job; None when that did not apply."""
        now = utcnow()
        with self.sessionmaker() as s:
            r = claim_task(s, task_id=task_id, worker_id=self.worker_id, now=now,
                           lease_until=now + timedelta(seconds=self.settings.lease_s))
        if r is None:
            return None
        return _Claimed(task_id, int(r.job_id), int(r.space_id), int(r.point_idx), int(r.view_idx), str(r.cue),
                        int(r.attempts))  # RETURNING gives the new values: attempts counts this attempt

    def _blocked(self, s: Session, job_id: int, now: Any) -> bool:
        return s.execute(
            select(WorkerBlock.job_id).where(
                WorkerBlock.worker_id == self.worker_id, WorkerBlock.job_id == job_id,
                or_(WorkerBlock.until.is_(None), WorkerBlock.until > now),
            )
        ).first() is not None

    def _move_mine(self, s: Session, t: _Claimed, to_state: str, **values: Any) -> bool:
        """running -> to_state for a task still held by this worker; counters follow (states.transition)."""
        return bool(transition(s, job_id=t.job_id, task_ids=[t.id], from_state=TaskState.RUNNING, to_state=to_state,
                               where=[Task.worker_id == self.worker_id], **values))

    def _record_done(self, t: _Claimed, key: str, info: Any, duration: float) -> Outcome:
        def step() -> bool:
            with self.sessionmaker() as s:
                return finish_task(s, task_id=t.id, job_id=t.job_id, worker_id=self.worker_id, key=key,
                                   size=int(info.size), sha256=info.sha256, duration_s=float(duration), now=utcnow())

        try:
            ok = self._db(step, f"record task {t.id} done")
        except Exception as exc:
            log.error("task %d: output stored at %s but not recorded (%s); the reaper will retry it",
                      t.id, key, format_error(exc, 0))
            return Outcome(t.id, "lost", t.cue, t.job_id, key, info.size, info.sha256, format_error(exc), duration)
        status = "done" if ok else "discarded"
        if not ok:
            log.info("task %d finished but is no longer ours (reaped or cancelled); result discarded", t.id)
        return Outcome(t.id, status, t.cue, t.job_id, key, int(info.size), info.sha256, None, duration)

    def _record_failure(self, t: _Claimed, exc: BaseException, duration: float) -> Outcome:
        error = format_error(exc)
        log.warning("task %d (%s, job %d) failed on attempt %d: %s", t.id, t.cue, t.job_id, t.attempts,
                    error.splitlines()[0])

        def step() -> str:
            now = utcnow()
            max_attempts = self._max_attempts(t.job_id)
            with self.sessionmaker() as s:
                if t.attempts < max_attempts:
                    status = "retry"
                    ok = self._move_mine(
                        s, t, TaskState.PENDING, error=error, lease_until=None, queued_at=None, worker_id=None,
                        not_before=now + timedelta(seconds=retry_backoff_s(t.attempts)),
                    )
                else:
                    status = "failed"
                    ok = self._move_mine(s, t, TaskState.FAILED, error=error, lease_until=None, finished_at=now,
                                         duration_s=float(duration))
                self._count_failure(s, t.job_id, now)
                s.commit()
                return status if ok else "discarded"

        try:
            status = self._db(step, f"record failure of task {t.id}")
        except Exception as db_exc:
            log.error("task %d: could not record its failure (%s); the reaper will retry it", t.id,
                      format_error(db_exc, 0))
            status = "lost"
        return Outcome(t.id, status, t.cue, t.job_id, error=error, duration_s=duration)

    def _count_failure(self, s: Session, job_id: int, now: Any) -> None:
        """One more failure of this worker on the job; every BLOCK_AFTER_FAILURES-th keeps it off for a while."""
        block = s.get(WorkerBlock, (self.worker_id, job_id))
        if block is None:
            # `until` None would mean "for good": an unblocked row carries a time in the past.
            block = WorkerBlock(worker_id=self.worker_id, job_id=job_id, failures=0, until=now)
            s.add(block)
        block.failures = int(block.failures or 0) + 1
        if block.failures % BLOCK_AFTER_FAILURES == 0:
            block.until = now + BLOCK_FOR
            log.warning("worker %s failed %d times on job %d: kept off it until %s", self.worker_id,
                        block.failures, job_id, block.until.isoformat())

    def _max_attempts(self, job_id: int) -> int:
        info = self._jobs.get(job_id)
        return info.spec.max_attempts if info is not None else self.settings.max_attempts

    # ------------------------------------------------------------------------------------------ loading

    def _job(self, job_id: int) -> _JobInfo:
        info = self._jobs.get(job_id)
        if info is None:
            def load() -> _JobInfo:
                with self.sessionmaker() as s:
                    job = s.get(Job, job_id)
                    if job is None:
                        raise LookupError(f"job {job_id} does not exist")
                    spec = JobSpec.model_validate(job.spec)
                    return _JobInfo(job.id, spec, job_root(job), job.name or spec.name)

            info = self._db(load, f"load job {job_id}")
            self._jobs[job_id] = info
        return info

    def _space(self, space_id: int) -> Space:
        space = self._spaces.get(space_id)
        if space is None:
            def load() -> Space:
                with self.sessionmaker() as s:
                    row = s.get(Space, space_id)
                    if row is None:
                        raise LookupError(f"space {space_id} does not exist")
                    s.expunge(row)
                    return row

            space = self._db(load, f"load space {space_id}")
            self._spaces[space_id] = space
        return space

    def _root_key(self, job: _JobInfo, key: str) -> str:
        return f"{job.root}/{key}" if job.root else key

    def _plan(self, job: _JobInfo, space: Space) -> SpacePlan:
        k = (job.id, space.id)
        plan = self._plans.get(k)
        if plan is None:
            plan = plan_from_json(self.store.get_bytes(self._root_key(job, f"_plan/{space.name}.json")))
            self._plans[k] = plan
            while len(self._plans) > PLAN_CACHE_SIZE:
                self._plans.popitem(last=False)
        else:
            self._plans.move_to_end(k)
        return plan

    def _space_context(self, job: _JobInfo, space: Space) -> Any:
        """The space loaded into the world frame of this job (its up_axis/unit_scale), kept between tasks."""
        from services.core.space_registry import fetch_space
        from services.core.spaces import load_space
        from services.worker.space_cache import SpaceContext

        spec = job.spec
        key = f"{space.checksum}:{json.dumps(spec.space_frame(), sort_keys=True)}"

        def loader() -> SpaceContext:
            path = fetch_space(self.store, space, self.cache_dir)
            loaded = load_space(path, **spec.space_frame())
            return SpaceContext.from_loaded(loaded, key=key, device=self.render_device, threads=self.render_threads)

        return self.space_cache.get(key, loader)

    # ------------------------------------------------------------------------------------------ compute

    def _view_context(self, t: _Claimed, job: _JobInfo, space: Space, plan: SpacePlan, view: Any) -> Any:
        """A ViewContext holding the view's pass set: memory LRU, else the store's pass cache, else a render."""
        from services.worker.context import ViewContext
        from services.worker.passes import ViewPasses
        from services.worker.space_cache import SpaceContext

        vk = (t.job_id, t.space_id, t.point, t.view)
        ctx = self._views.get(vk)
        if ctx is not None:
            self._views.move_to_end(vk)
            return ctx
        params = job.spec.params
        pkey = self._root_key(job, passes_key(space.name, t.point, t.view))
        passes = None
        if t.cue != "passes":
            try:
                passes = ViewPasses.from_bytes(self.store.get_bytes(pkey))
            except FileNotFoundError:  # the cache was cleared (job finished, then resumed): render again
                log.info("task %d: no cached pass set at %s; rendering the view again", t.id, pkey)
        if passes is not None:
            ctx = ViewContext(view, params, passes=passes, plan=plan)
        else:
            space_ctx: SpaceContext = self._space_context(job, space)
            ctx = ViewContext(view, params, space=space_ctx, plan=plan, render_passes=self._job_passes(job))
            _ = ctx.passes  # render now, so the time is booked to this task
            self.renders += 1
        self._views[vk] = ctx
        trim_lru(self._views, int(VIEW_CACHE_MEMORY_FRACTION * self.settings.worker_max_memory_mb * 2**20))
        return ctx

    @staticmethod
    def _job_passes(job: _JobInfo) -> frozenset[str]:
        """The render passes the job's cues read: the cached pass set holds those only."""
        from services.core.cues import OUTPUT_CUES
        from services.worker.executor import render_passes_for

        return render_passes_for(job.spec.cues if job.spec.cues is not None else OUTPUT_CUES)

    def _execute(self, t: _Claimed) -> tuple[str, Any]:
        """Compute the task's bytes and store them at the deterministic key; returns (key, ObjectInfo)."""
        from services.worker.context import ViewContext
        from services.worker.executor import produce

        job = self._job(t.job_id)
        space = self._space(t.space_id)
        plan = self._plan(job, space)
        view = plan.view(t.point, t.view)
        if t.cue == "passes":
            ctx = self._view_context(t, job, space, plan, view)
            key = self._root_key(job, passes_key(space.name, t.point, t.view))
        else:
            if _needs_passes(t.cue):
                ctx = self._view_context(t, job, space, plan, view)
            else:  # plan cues (point_info, nonfixated, vanishing_points) need no render
                ctx = ViewContext(view, job.spec.params, plan=plan)
            key = self._root_key(job, output_key(t.cue, job.component, space.name, t.point, t.view))
        data = produce(t.cue, ctx)
        info = self.store.put_bytes(key, data)
        return key, info


def trim_lru(views: OrderedDict[Any, Any], budget_bytes: int, keep: int = VIEW_CACHE_MIN) -> None:
    """Drop the least recently used entries (first in `views`, each with .nbytes()) while they hold more than
    budget_bytes, keeping at least the `keep` most recent."""
    sizes = [c.nbytes() for c in views.values()]
    total = sum(sizes)
    for size in sizes[:max(0, len(sizes) - keep)]:
        if total <= budget_bytes:
            break
        views.popitem(last=False)
        total -= size


def default_worker_id(name: str | None = None) -> str:
    """This process's worker id: `name` (the worker's --hostname) plus `-<i>` for pool child i > 0, so it
    stays the same when Celery replaces a recycled child; `host:pid` without a name."""
    import socket

    from celery.utils.log import current_process_index

    if not name:
        return f"{socket.gethostname()}:{os.getpid()}"
    index = current_process_index(base=0)  # pool child 0, 1, ...; None outside a pool
    return f"{name}-{index}" if index else name
