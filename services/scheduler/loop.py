"""The scheduler loop: plan claimed jobs, dispatch ready tasks, reap lost ones, finish completed jobs.

Each step opens its own short session, so a dropped database connection (Postgres restarted) costs one
failed step: `run_forever` logs it, backs off and carries on; the engine's pool_pre_ping reconnects.
Several schedulers may run at once: job claims use SKIP LOCKED and every task move is conditional.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field
from multiprocessing.sharedctypes import Synchronized
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.engine import make_engine, make_sessionmaker
from services.core.db.frame_choice import space_frame_for
from services.core.db.jobs import claim_pending_jobs, job_spaces, job_spec
from services.core.db.models import Job, JobState, Space
from services.core.db.plan_claims import tenants_waiting_idle
from services.core.db.states import set_job_state
from services.core.db.worker_rows import expire_worker_rows
from services.core.domain.jobspec import JobSpec, SpaceFrame
from services.core.domain.plan_budget import check_plan_budget
from services.core.ingest.loading import LoadedSpace
from services.core.settings import Settings
from services.core.storage import LocalStore, ObjectStore, open_store
from services.core.storage.base import io_pool
from services.scheduler.chunked_plan import ChunkTarget, PlanDropped, plan_and_persist_space
from services.scheduler.compaction import CompactionResult, Compactor
from services.scheduler.completion import Finished, complete_once
from services.scheduler.dispatch import DEFAULT_BUDGET, DispatchResult, dispatch_once
from services.scheduler.fairness import CAPPED_WAIT_S, queued_cap
from services.scheduler.persist import clear_plan, drop_cancelled_plan, plan_key
from services.scheduler.plan_failure import PlanningError, record_planning_failure
from services.scheduler.plan_space import JobPlanSummary, load_for_job, plan_summary_of
from services.scheduler.planner_proc import (
    PlannerProcesses,
    count_connections,
    die_with_scheduler,
    limit_memory,
)
from services.scheduler.reaper import ReapResult, reap_once
from services.scheduler.resend import IdleWatch, resend_stuck
from services.scheduler.store_watch import StoreWatch
from services.scheduler.transport import NullTransport, Transport

log = logging.getLogger(__name__)

REAP_INTERVAL_S = 5.0
THOROUGH_DISPATCH_S = 60.0  # a dispatch pass that ignores the counter-based scan bounds (a safety net) ...
THOROUGH_STALLED_S = 5.0  # ... and sooner when a job has pending tasks but nothing ready or in flight
COMPACT_INTERVAL_S = 1.0  # finished views compacted at most this often (each pass bounded by compact_pass_s)
# completion's own look at the counters; sooner when a dispatch pass saw a job settle
COMPLETE_INTERVAL_S = 2.0
MAX_BACKOFF_S = 30.0
# A local folder's temp files of writes that never committed (a worker killed mid-write) are swept this often,
# on a thread (a walk of the folder), once idle for TEMP_STALE_S: a write in flight touches its file every
# chunk and renames it within seconds.
TEMP_SWEEP_INTERVAL_S = 600.0
TEMP_STALE_S = 600.0


def loaded_space_key(checksum: str, frame: SpaceFrame) -> str:
    """What a loaded space is known by in `Scheduler(loaded_spaces=...)`: its stored source and its frame."""
    return f"{checksum}:{json.dumps(frame, sort_keys=True)}"


def default_scheduler_id() -> str:
    """`host:pid` of this process."""
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclass
class TickResult:
    """What one tick did."""

    planned: list[int] = field(default_factory=list)
    dispatched: DispatchResult = field(default_factory=DispatchResult)
    reaped: ReapResult | None = None
    finished: list[Finished] = field(default_factory=list)
    compacted: CompactionResult | None = None
    resumed: list[int] = field(default_factory=list)  # jobs held for their store, resumed now

    budget: int = DEFAULT_BUDGET

    @property
    def busy(self) -> bool:
        """Whether there is probably more work right away (a full dispatch budget or a job planned)."""
        return bool(self.planned) or self.dispatched.sent >= self.budget


def _log_sweep(done: Future[int]) -> None:
    if done.exception() is not None:
        log.warning("sweeping the object folder's temp files failed: %s", done.exception())
    elif done.result():
        log.info("removed %d temp files of writes that never committed", done.result())


class Scheduler:
    """One scheduler process: plans jobs, dispatches tasks, reaps lost tasks and finishes jobs."""

    def __init__(
        self,
        sessionmaker: sessionmaker[Session],
        store: ObjectStore,
        transport: Transport,
        settings: Settings,
        scheduler_id: str | None = None,
        *,
        cache_dir: Path | None = None,
        budget: int = DEFAULT_BUDGET,
        plan_in_processes: bool = False,
        cap_queue: bool = False,
        loaded_spaces: dict[str, LoadedSpace] | None = None,
    ) -> None:
        self.sessionmaker = sessionmaker
        self.store = store
        self.transport = transport
        self.settings = settings
        self.scheduler_id = scheduler_id or default_scheduler_id()
        self.cache_dir = cache_dir or settings.data_dir / "cache" / "spaces"
        self.budget = budget
        self._rotation = 0
        self._last_reap = 0.0
        self._last_complete = 0.0
        self._last_compact = 0.0
        self.compactor = (
            Compactor(sessionmaker, after_s=settings.compact_after_s, pass_s=settings.compact_pass_s)
            if settings.compact_views
            else None
        )
        self._last_thorough = time.monotonic()  # the first passes use the (cheap) bounded scans
        self._stalled = False
        self._idle_watch = IdleWatch()
        self.store_watch = StoreWatch(sessionmaker, store)
        self._last_sweep = -TEMP_SWEEP_INTERVAL_S  # the first reaper pass sweeps
        self.sweep: Future[int] | None = None
        # The service plans in child processes (off this loop, memory-capped, leases beaten every tick); the
        # embedded runner and tests plan inline.
        self.planners = (PlannerProcesses(sessionmaker, settings, self.scheduler_id, plan_in_child)
                         if plan_in_processes else None)
        # The service keeps the broker queue short (tenants share it fairly); the embedded runner, with one
        # user and local workers fed between rate-limited ticks, keeps the whole window queued.
        self.cap_queue = cap_queue
        # Spaces the caller has already loaded (`omnidata generate` validated them), by `loaded_space_key`:
        # the next job planned takes them instead of parsing them a second time (~2 CPU-s a room); the dict is
        # taken over and emptied then, so no mesh stays in this process.
        self.loaded_spaces = loaded_spaces if loaded_spaces is not None else {}

    # ------------------------------------------------------------------------------------------ planning

    def fetch_source(self, space: Space) -> Path:
        """Local path of a space's mesh, downloaded (and unzipped) once per checksum into the cache folder."""
        from services.core.ingest.registry import fetch_space

        return Path(fetch_space(self.store, space, self.cache_dir))

    def load_space(self, space: Space, spec: JobSpec) -> LoadedSpace:
        """The space in the frame the job plans it in: the caller's loaded copy when it was loaded from the
        same source (checksum) in the same frame, else loaded from the store's copy."""
        frame = space_frame_for(spec, space)
        given = self.loaded_spaces.pop(loaded_space_key(space.checksum, frame), None)
        return given if given is not None else load_for_job(self.fetch_source(space), spec, frame=frame)

    def plan_pending(self, limit: int = 1) -> list[int]:
        """Claim up to `limit` pending jobs and plan them; returns the ids of jobs now running (with planner
        processes: starts them, and returns the ids of jobs whose planning ended)."""
        if self.planners is not None:
            ended = self.planners.watch()
            if self.planners.children:  # a plan may have to yield its slot, or a paused one may go on
                with self.sessionmaker() as s:
                    self.planners.make_room(bool(tenants_waiting_idle(s)))
            if self.planners.free > 0:
                with self.sessionmaker() as s:
                    jobs = claim_pending_jobs(s, self.scheduler_id, min(limit, self.planners.free),
                                              lease_s=self.settings.heartbeat_timeout_s)
                    claimed = [(j.id, j.owner) for j in jobs]
                    s.commit()
                for job_id, owner in claimed:
                    self.planners.start(job_id, owner)
            return ended
        with self.sessionmaker() as s:
            jobs = claim_pending_jobs(s, self.scheduler_id, limit)
            ids = [j.id for j in jobs]
            s.commit()
        planned = []
        for job_id in ids:
            if self.plan_job(job_id):
                planned.append(job_id)
        return planned

    def plan_job(self, job_id: int) -> bool:
        """Plan a job this scheduler has claimed, chunk by chunk (services.scheduler.chunked_plan), each chunk
        in its own transaction, and the job's switch to running in the last; True when it is now running."""
        t0 = time.perf_counter()
        spec: JobSpec | None = None
        try:
            with self.sessionmaker() as s:
                job = s.get(Job, job_id)
                if job is None or job.state != JobState.PLANNING or job.planner != self.scheduler_id:
                    return False
                spec = job_spec(job)
                # refused before any work: a spec over the planning budget (the API refuses it too)
                check_plan_budget(
                    spec, memory_mb=self.settings.plan_memory_mb, timeout_s=self.settings.plan_timeout_s,
                    chunk_views=self.settings.plan_chunk_views,
                )
                clear_plan(s, job.id)  # the chunks an earlier attempt left
                attempts = (job.plan_summary or {}).get("attempts", 0) + 1
                spaces = [
                    (list(js.cues), space, plan_key(job, space.name)) for js, space in job_spaces(s, job.id)
                ]
                s.expunge_all()
                s.commit()
            summary: JobPlanSummary = {"spaces": {}, "attempts": attempts}
            target = ChunkTarget(self.sessionmaker, self.store, job_id, self.scheduler_id,
                                 self.settings.plan_chunk_views)
            total = 0
            for cues, space, key in spaces:
                loaded = self.load_space(space, spec)
                done = plan_and_persist_space(target, loaded, spec, space, cues, key)
                if not done.views:
                    raise PlanningError(
                        f"space {space.name!r} yields no views"
                        + (f": {done.whole.shortfall}" if done.whole.shortfall else
                           " (no point is seen by enough cameras)"))
                total += done.tasks
                summary["spaces"][space.name] = {
                    "cameras": done.cameras, "points": done.points, "views": done.views, "tasks": done.tasks,
                    "plan_key": key, **plan_summary_of(loaded, done.whole, spec),
                    "distributions": done.distributions,
                }
            summary["shortfall"] = any(v["shortfall"] for v in summary["spaces"].values())
            summary["planning_s"] = round(time.perf_counter() - t0, 3)
            if not self._planned(job_id, total, summary):
                return False
        except PlanDropped:
            log.info("job %d changed while planning; plan dropped", job_id)
            drop_cancelled_plan(self.sessionmaker, job_id)
            return False
        except Exception as exc:
            self._planning_failed(job_id, exc, spec)
            return False
        finally:
            self.loaded_spaces.clear()
        log.info("job %d planned: %d tasks in %.2f s", job_id, total, time.perf_counter() - t0)
        return True

    def _planned(self, job_id: int, total: int, summary: JobPlanSummary) -> bool:
        """Switch a planned job to running, unless it was cancelled (or taken over) meanwhile."""
        with self.sessionmaker() as s:
            stmt = select(Job).where(Job.id == job_id).execution_options(populate_existing=True)
            if s.get_bind().dialect.name == "postgresql":
                stmt = stmt.with_for_update(key_share=True)  # FOR NO KEY UPDATE
            job = s.scalars(stmt).one()
            if job.state != JobState.PLANNING or job.planner != self.scheduler_id:
                log.info("job %d changed to %s while planning; plan dropped", job_id, job.state)
                return False
            set_job_state(
                job, JobState.RUNNING, total_tasks=total, plan_summary=summary, planner_lease_until=None
            )
            s.commit()
        return True

    def _planning_failed(self, job_id: int, exc: BaseException, spec: JobSpec | None) -> None:
        if isinstance(exc, MemoryError):
            # a photo that ran out decoding says so itself (PhotoRefused); past that, photos are still held
            photos = spec is not None and (spec.uses_photos() or spec.cameras.mode == "capture")
            advice = ("downscale the capture's photos, or lower points.count or points.max_views" if photos
                      else "lower points.count or points.max_views")
            exc = PlanningError(f"planning ran out of its memory budget of {self.settings.plan_memory_mb} MB "
                                f"(OMNIDATA_PLAN_MEMORY_MB): {advice}")
        record_planning_failure(self.sessionmaker, job_id, self.scheduler_id, exc)

    # ------------------------------------------------------------------------------------------ steps

    def dispatch_once(self) -> DispatchResult:
        """Dispatch ready tasks of running jobs (window, priorities, fairness)."""
        since = time.monotonic() - self._last_thorough
        thorough = since >= THOROUGH_DISPATCH_S or (self._stalled and since >= THOROUGH_STALLED_S)
        t0 = time.perf_counter()
        with self.sessionmaker() as s:
            res = dispatch_once(
                s, self.transport, window=self.settings.dispatch_window, budget=self.budget,
                rotation=self._rotation, thorough=thorough,
                queued_cap=queued_cap(s, alive_within_s=self.settings.heartbeat_timeout_s)
                if self.cap_queue
                else None,
            )
        if thorough:
            self._last_thorough = time.monotonic()
        self._stalled = bool(res.stalled)
        log.debug("dispatch pass: %d sent in %.3f s%s", res.sent, time.perf_counter() - t0,
                  " (thorough)" if thorough else "")
        self._rotation += 1
        return res

    def reap_once(self) -> ReapResult:
        """Return dead workers' tasks, expired and lost tasks to pending (or fail them when out of
        attempts)."""
        with self.sessionmaker() as s:
            res = reap_once(
                s, queued_timeout_s=self.settings.lease_s, default_max_attempts=self.settings.max_attempts,
                dead_after_s=self.settings.heartbeat_timeout_s,
            )
            expire_worker_rows(s, older_than_s=self.settings.worker_expiry_s)
        if self.planners is not None:
            self.planners.sweep()
        with self.sessionmaker() as s:  # messages a dead worker held, or stuck while workers sit idle
            resend_stuck(
                s, self.transport, self.settings, self._idle_watch,
                dead_after_s=self.settings.heartbeat_timeout_s,
                stuck_after_s=self.settings.heartbeat_timeout_s,
            )
        self._last_reap = time.monotonic()
        self.sweep_temp_files()
        return res

    def sweep_temp_files(self) -> None:
        """Start a sweep of the local folder's stale temp files (LocalStore.remove_temp_files) on a thread, at
        most every TEMP_SWEEP_INTERVAL_S; S3 keeps none (an interrupted upload is never an object)."""
        if not isinstance(self.store, LocalStore):
            return
        if time.monotonic() - self._last_sweep < TEMP_SWEEP_INTERVAL_S:
            return
        if self.sweep is not None and not self.sweep.done():
            return
        self._last_sweep = time.monotonic()
        self.sweep = io_pool().submit(self.store.remove_temp_files, TEMP_STALE_S)
        self.sweep.add_done_callback(_log_sweep)

    def complete_once(self) -> list[Finished]:
        """Finish running jobs with nothing left to do (manifest, job.json, pass cache removed)."""
        with self.sessionmaker() as s:
            return complete_once(s, self.store)

    def tick(self, *, plan: bool = True) -> TickResult:
        """One round of every step (the reaper only every REAP_INTERVAL_S, completion when a job settled).
        `plan=False` skips planning: a caller that knows no job waits for it (the embedded run's one job,
        planned)."""
        res = TickResult(budget=self.budget)
        if plan:
            res.planned = self.plan_pending()
        if time.monotonic() - self._last_reap >= REAP_INTERVAL_S:
            res.reaped = self.reap_once()
        res.resumed = self.store_watch.check()
        res.dispatched = self.dispatch_once()
        # the dispatch pass has just read every running job's counters: completion's own read of them (a scan
        # of each job's counter shards) is needed only when a job settled there, or now and then as a safety
        # net
        if res.dispatched.settled or time.monotonic() - self._last_complete >= COMPLETE_INTERVAL_S:
            res.finished = self.complete_once()
            self._last_complete = time.monotonic()
        if self.compactor is not None and time.monotonic() - self._last_compact >= COMPACT_INTERVAL_S:
            res.compacted = self.compactor.run_once()
            self._last_compact = time.monotonic()
        return res

    def run_forever(self, stop_event: threading.Event, interval: float = 1.0) -> None:
        """Tick until `stop_event` is set; errors (a database restart) are logged and backed off, never
        fatal."""
        backoff = 0.0
        log.info("scheduler %s started (interval %.1f s)", self.scheduler_id, interval)
        while not stop_event.is_set():
            try:
                res = self.tick()
            except Exception as exc:
                backoff = min(MAX_BACKOFF_S, max(1.0, backoff * 2))
                log.error(
                    "scheduler tick failed (%s: %s); retrying in %.0f s", type(exc).__name__, exc, backoff
                )
                log.debug("tick failure", exc_info=True)
                stop_event.wait(backoff)
                continue
            if backoff:
                log.info("scheduler recovered")
            backoff = 0.0
            if res.dispatched.sent or res.planned or res.finished:
                log.debug("tick: planned %s, sent %d, finished %s", res.planned, res.dispatched.sent,
                          [f.job_id for f in res.finished])
            if res.dispatched.capped:  # workers drain a short queue fast: top it up soon
                stop_event.wait(min(interval, CAPPED_WAIT_S))
            elif not res.busy:
                stop_event.wait(interval)
        if self.planners is not None:
            self.planners.stop_all()
        log.info("scheduler %s stopped", self.scheduler_id)


def plan_in_child(
    job_id: int, scheduler_id: str, settings: Settings, scheduler_pid: int, in_db: Synchronized,
) -> None:
    """Child process entry: plan and persist one job under the memory budget, as its claiming scheduler."""
    die_with_scheduler(scheduler_pid)
    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(levelname)s planner %(process)d: %(message)s")
    limit_memory(settings.plan_memory_mb)
    engine = make_engine(settings.database_url)
    count_connections(engine, in_db)
    try:
        store = open_store(settings.storage_url, settings)
        sched = Scheduler(make_sessionmaker(engine), store, NullTransport(), settings, scheduler_id)
        sched.plan_job(job_id)
    finally:
        engine.dispose()
