"""TaskRunner: run one task of the execution contract.

    runner = TaskRunner(sessionmaker, store, settings, worker_id)
    outcome = runner.run(task_id)

1. Claim the task (services.worker.claim: queued -> running, or why not).
2. Load the job spec, the space (kept loaded between tasks: SpaceCache) and the plan JSON (services.worker.caches).
3. Compute: the `passes` task renders the view once into this process's memory; every other cue is derived from
   that pass set, read from this process's memory LRU or the store's pass cache (.npz, written only when a task of
   the view may need it after the view batch below), and rendered again only if the cache is gone (e.g. after
   a resume of a finished job).
4. Write the objects atomically to their deterministic keys, a batch's together (store.put_many: one wait for
   the disk or the network a view), then record them done (services.worker.claim).
   View batch (settings.worker_batch_views): the worker that rendered a view's `passes` claims, in one
   statement, the rest of that view's tasks, pending or queued (every DAG level: all their inputs are cues of
   the view, computed in memory by its ViewContext in topological order), derives and stores each, and records
   them all done, `passes` included, in one statement: ~3 statements a view instead of ~2 per task. When the
   batch made every task of the view that reads the pass set, the pass set is never stored (`passes` is
   recorded with size 0, no sha256). A derived cue's task (a view the batch did not take whole: rendered by a
   renderer of `generate --render-workers`, which stores the pass set and leaves the view to the others
   (hand_off_views); a retry; a resume) claims its view's queued tasks alike, and when it reads the pass set (so
   the pass set is done) the pending ones too: the pass set, read once, gives every cue of the view, where
   queued-only took one batch and one read of the pass set per DAG level.
   Each task keeps its row; a pending task claimed so gets no message, a queued one's message is skipped when
   it comes (a read, no claim). A task whose input failed in the batch is handed back to pending unrun. A batch
   whose worker dies stays `running` under its lease (the beats extend all of it): the reaper re-queues every
   task of it.
5. Failure: retry after a backoff or fail for good, and keep a failing worker off the job
   (services.worker.failure_policy); a store that fails (full, S3 5xx) holds the job instead, its tasks'
   attempts not counted (TaskLedger.hold_for_storage), until the scheduler sees the store take writes again.

Bytes, not files, flow through here; all geometry is in the plan (world metres, OpenCV camera axes).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from sqlalchemy.orm import Session

from services.core.db.models import Space
from services.core.domain.cues import CATALOG, OUTPUT_CUES, closure
from services.core.domain.keys import output_key, passes_key
from services.core.domain.plan import PlannedView, SpacePlan
from services.core.ingest.loading import load_space
from services.core.ingest.registry import fetch_space
from services.core.settings import Settings
from services.core.storage import ObjectInfo, ObjectStore, storage_outage
from services.worker.caches import VIEW_CACHE_MEMORY_FRACTION, JobInfo, TaskInputs
from services.worker.claim import DB_RETRY_S, Claimed, Outcome, TaskLedger
from services.worker.context import ViewContext
from services.worker.executor import produce, render_passes_for
from services.worker.heartbeat import Heartbeat
from services.worker.loaded_cache import read_loaded
from services.worker.passes import ViewPasses
from services.worker.space_cache import SpaceCache, SpaceContext, should_recycle
from services.worker.stop_signal import reraise_stop

Recorded = tuple[Claimed, str, ObjectInfo, float]  # a stored task: its key, object and seconds

log = logging.getLogger(__name__)

BATCHED_MEMORY = 4096  # task ids of recent view batches remembered, so their late messages skip the claim


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
        heartbeat: Heartbeat | None = None,
        cache_dir: str | Path | None = None,
        render_threads: int | None = None,
        render_device: str | None = None,
        db_retry_s: float = DB_RETRY_S,
        hand_off_views: bool = False,
    ) -> None:
        self.sessionmaker = sessionmaker
        self.store = store
        self.settings = settings
        self.worker_id = worker_id
        self.heartbeat = heartbeat
        self.cache_dir = Path(cache_dir) if cache_dir is not None else settings.data_dir / "cache" / "spaces"
        self.render_threads = render_threads if render_threads is not None else settings.render_threads
        self.render_device = render_device or settings.render_device
        self.db_retry_s = db_retry_s
        # A renderer of `generate --render-workers`: a `passes` task stores its pass set for the workers that only
        # derive, instead of deriving the view itself (a view batch).
        self.hand_off_views = hand_off_views
        self.ledger = TaskLedger(sessionmaker, worker_id, settings.lease_s, db_retry_s)
        self.inputs = TaskInputs(sessionmaker, store, self.ledger.db,
                                 int(VIEW_CACHE_MEMORY_FRACTION * settings.worker_max_memory_mb * 2**20))
        self.space_cache = SpaceCache()
        # Messages run (a view batch is one, like Celery's worker_max_tasks_per_child counts it): the recycle count.
        self.tasks_run = 0
        self.renders = 0  # pass sets rendered by this process (one per view, unless a cache was lost)
        self.batched: deque[int] = deque(maxlen=BATCHED_MEMORY)  # ids this process ran in view batches lately

    def run(self, task_id: int) -> Outcome:
        """Claim and run one task, and with it the rest of its view (a view batch, when
        settings.worker_batch_views): after a `passes` task, the view's pending and queued tasks; after a derived
        cue's, the view's queued ones, and pending ones too when it reads the pass set. Never raises for task
        failures (they are recorded), only TransientError. The returned Outcome is the message's task's; `batch`
        holds the others'."""
        t0 = time.perf_counter()
        if task_id in self.batched and self.ledger.is_settled(task_id):
            # Its message came after a view batch of ours ran it: no claim attempt (no write lock) for a no-op.
            return Outcome(task_id, "skipped", error="done in a view batch (duplicate message)")
        claimed = self.ledger.claim(task_id)
        if isinstance(claimed, Outcome):
            return claimed
        self.tasks_run += 1
        if self.heartbeat is not None:
            self.heartbeat.set_current(claimed.id)
        try:
            if not self.settings.worker_batch_views:
                outcomes = self._run_claimed([claimed], t0)
            elif claimed.cue == "passes":
                outcomes = self._hand_off_view(claimed, t0) if self.hand_off_views else self._run_view(claimed, t0)
            else:
                outcomes = self._run_derived(claimed, t0)
        finally:
            if self.heartbeat is not None:
                self.heartbeat.set_current(None)
        if self.heartbeat is not None:
            for o in outcomes:
                if o.status in ("done", "retry", "failed", "discarded"):
                    self.heartbeat.record_done(str(o.cue), o.labels)
        return replace(outcomes[0], batch=tuple(outcomes[1:]), recycle=self.should_recycle())

    def _claim_rest(self, claimed: Claimed, *, with_pending: bool) -> tuple[list[Claimed], bool]:
        """The rest of the claimed task's view (ledger.claim_view_rest), remembered, and leased by the beats."""
        rest, elsewhere = self.ledger.claim_view_rest(claimed, with_pending=with_pending)
        self.batched.extend(c.id for c in rest)
        if self.heartbeat is not None:
            self.heartbeat.set_current(claimed.id, [c.id for c in rest])
        return rest, elsewhere

    def _run_view(self, passes: Claimed, t0: float) -> list[Outcome]:
        """The whole view on this worker: render its pass set (the `passes` task) into memory, claim the rest of
        the view in one statement, derive it, and record everything done in one statement. The pass set is
        stored only when a task of the view that reads it may run later (not claimed, failed or handed back):
        otherwise nobody reads it (a re-run after a resume renders again), and `passes` is recorded with size 0
        and no sha256, and the view's context leaves the memory LRU at once: kept, the LRU's budget held ~60 views'
        arrays, so every view wrote into fresh pages (1.6 GB of page faults a 66-view run, ~30 ms a view). A failed
        render is recorded alone: the rest of the view stays pending."""
        try:
            key = self.render_view(passes)
        except Exception as exc:
            reraise_stop(exc)
            return [self._record_failure(passes, exc, t0)]
        render_s = time.perf_counter() - t0
        rest, elsewhere = self._claim_rest(passes, with_pending=True)
        done, failed = self._compute(rest, time.perf_counter())
        info = ObjectInfo(key, 0, None)
        t1 = time.perf_counter()
        if elsewhere or len(done) < len(rest):
            try:
                key, info = self.execute(passes)  # serialised from the pass set in memory, and stored
            except Exception as exc:
                reraise_stop(exc)
                failed[passes.id] = self._record_failure(passes, exc, t1 - render_s)
        if passes.id not in failed:
            done.insert(0, (passes, key, info, render_s + time.perf_counter() - t1))
        if not elsewhere and not failed:  # nothing of the view is left to run: free its arrays for the next view
            self.inputs.forget_view((passes.job_id, passes.space_id, passes.point, passes.view))
        return self._record([passes, *rest], done, failed)

    def _hand_off_view(self, passes: Claimed, t0: float) -> list[Outcome]:
        """Render the view and store its pass set for whoever derives it; its arrays leave this process at once."""
        outcomes = self._run_claimed([passes], t0)
        self.inputs.forget_view((passes.job_id, passes.space_id, passes.point, passes.view))
        return outcomes

    def _run_derived(self, claimed: Claimed, t0: float) -> list[Outcome]:
        """A derived cue's task and the rest of its view this worker could claim: the queued tasks, and the pending
        ones too when it reads the pass set (module docstring). Once nothing of the view reads the pass set any
        more, its arrays leave the memory LRU (see _run_view)."""
        reads = _needs_passes(claimed.cue)
        rest, elsewhere = self._claim_rest(claimed, with_pending=reads)
        outcomes = self._run_claimed([claimed, *rest], t0)
        if reads and not elsewhere and all(o.status == "done" for o in outcomes):  # elsewhere also when none claimed
            self.inputs.forget_view((claimed.job_id, claimed.space_id, claimed.point, claimed.view))
        return outcomes

    def _record_failure(self, t: Claimed, exc: Exception, t0: float) -> Outcome:
        outage = storage_outage(exc)
        if outage is not None:  # the store failed, not the task: it waits for the store, uncounted
            return self.ledger.hold_for_storage([t], outage)[0]
        max_attempts = self.inputs.max_attempts(t.job_id, self.settings.max_attempts)
        return self.ledger.record_failure(t, exc, time.perf_counter() - t0, max_attempts)

    def _run_claimed(self, claimed: list[Claimed], t0: float) -> list[Outcome]:
        """Compute, store and record claimed tasks (the first one's time counts from `t0`, its claim)."""
        done, failed = self._compute(claimed, t0)
        return self._record(claimed, done, failed)

    def _compute(self, claimed: list[Claimed], t0: float) -> tuple[list[Recorded], dict[int, Outcome]]:
        """Compute each claimed task in order, then store their files together (store.put_many); failures are
        recorded one by one, and a task an input of which failed here is handed back to pending unrun (the DAG's
        rule: a cue is queued when its inputs exist). Returns the stored tasks, and the Outcomes of the others by
        task id. A task's seconds are its computation's plus its share (by bytes) of the store's."""
        made: list[tuple[Claimed, str, bytes, float]] = []
        t_batch = t0
        try:
            for t in claimed:
                key, data = self.make(t)
                made.append((t, key, data, time.perf_counter() - t0))
                t0 = time.perf_counter()
            t1 = time.perf_counter()
            # A pass set is read again (by the view's other tasks elsewhere); the cues' files are not.
            infos = self.store.put_many([(key, data) for _, key, data, _ in made],
                                        keep_cached=any(t.cue == "passes" for t, _, _, _ in made))
        except Exception as exc:
            reraise_stop(exc)
            outage = storage_outage(exc)
            if outage is not None:  # the store is down or full: the whole batch waits for it, none re-run
                return [], {o.task_id: o for o in self.ledger.hold_for_storage(claimed, outage)}
            # Something failed: one task at a time, so each failure is recorded and only its dependents wait.
            return self._compute_one_by_one(claimed, t_batch)
        store_s, total = time.perf_counter() - t1, max(1, sum(len(d) for _, _, d, _ in made))
        return [(t, key, info, s + store_s * len(data) / total)
                for (t, key, data, s), info in zip(made, infos, strict=True)], {}

    def _compute_one_by_one(self, claimed: list[Claimed], t0: float) -> tuple[list[Recorded], dict[int, Outcome]]:
        """_compute's path when a task of the batch failed: compute and store each task on its own."""
        failed: dict[int, Outcome] = {}
        done: list[Recorded] = []
        unrun: list[Claimed] = []
        lost: set[str] = set()  # cues of this view that failed or were handed back in this batch
        failed_cues: list[str] = []
        for t in claimed:
            if lost.intersection(CATALOG[t.cue].inputs):
                unrun.append(t)
                lost.add(t.cue)
                continue
            try:
                key, info = self.execute(t)
            except Exception as exc:
                reraise_stop(exc)
                failed[t.id] = self._record_failure(t, exc, t0)
                lost.add(t.cue)
                failed_cues.append(t.cue)
            else:
                done.append((t, key, info, time.perf_counter() - t0))
            t0 = time.perf_counter()
        if unrun:
            why = f"handed back to pending unrun: {', '.join(failed_cues)} failed in its view batch"
            failed.update((o.task_id, o) for o in self.ledger.hand_back(unrun, why))
        return done, failed

    def _record(self, order: list[Claimed], done: list[Recorded], failed: dict[int, Outcome]) -> list[Outcome]:
        """Record the stored tasks done together (ledger.record_done_many); every Outcome, in `order`."""
        recorded = {o.task_id: o for o in self.ledger.record_done_many(done)} if done else {}
        return [failed.get(t.id) or recorded[t.id] for t in order]

    def should_recycle(self) -> bool:
        """True when this process should exit after the task: RSS above worker_max_memory_mb or worker_max_tasks
        messages run. A view batch counts once: counted by its ~18 tasks, a 66-view `generate` restarted its worker
        twice, each restart paying imports, the space load and Cycles' first render again (~3 CPU-s)."""
        return self.tasks_run >= self.settings.worker_max_tasks or should_recycle(self.settings.worker_max_memory_mb)

    def close(self) -> None:
        """Free the loaded space and cached views."""
        self.inputs.views.clear()
        self.space_cache.clear()

    def execute(self, t: Claimed) -> tuple[str, ObjectInfo]:
        """Compute the task's bytes and store them at the deterministic key; returns (key, ObjectInfo)."""
        key, data = self.make(t)
        return key, self.store.put_bytes(key, data)

    def make(self, t: Claimed) -> tuple[str, bytes]:
        """The task's deterministic key and file bytes (nothing stored)."""
        job = self.inputs.job(t.job_id)
        space = self.inputs.space(t.space_id)
        plan = self.inputs.plan(job, space)
        view = plan.view(t.point, t.view)
        if t.cue == "passes":
            ctx = self._view_context(t, job, space, plan, view)
            key = job.root_key(passes_key(space.name, t.point, t.view))
        else:
            if _needs_passes(t.cue):
                ctx = self._view_context(t, job, space, plan, view)
            else:  # plan cues (point_info, nonfixated, vanishing_points) need no render
                ctx = ViewContext(view, job.spec.params, plan=plan)
            key = job.root_key(output_key(t.cue, job.component, space.name, t.point, t.view))
        return key, produce(t.cue, ctx)

    def render_view(self, t: Claimed) -> str:
        """Render the view of a `passes` task into this process's memory (nothing stored); its pass set's key."""
        job = self.inputs.job(t.job_id)
        space = self.inputs.space(t.space_id)
        plan = self.inputs.plan(job, space)
        self._view_context(t, job, space, plan, plan.view(t.point, t.view))
        return job.root_key(passes_key(space.name, t.point, t.view))

    def _space_context(self, job: JobInfo, space: Space, plan: SpacePlan | None = None) -> SpaceContext:
        """The space loaded into the world frame of this job (its up_axis/unit_scale), kept between tasks."""
        spec = job.spec
        frame = job.frame_for(space)  # exactly the planner's: a re-pick of the space's up cannot change it
        capture = plan.capture if plan is not None else None
        refined = capture.get("refined") if capture is not None else None  # the planner's colour camera
        photos = f"{spec.uses_photos()}:{json.dumps(refined and refined['correction'], sort_keys=True)}"
        key = f"{space.checksum}:{json.dumps(frame, sort_keys=True)}:photos={photos}"

        def loader() -> SpaceContext:
            from services.worker.photos import painter_for

            # `omnidata generate` keeps the spaces it loaded in the run's cache folder: no second parse here
            cached = None if spec.uses_photos() else read_loaded(self.cache_dir, space.checksum, frame)
            if cached is not None:
                ctx = SpaceContext.from_loaded(cached, key=key, device=self.render_device, threads=self.render_threads)
            else:
                path = fetch_space(self.store, space, self.cache_dir)
                loaded = load_space(path, **frame)
                ctx = SpaceContext.from_loaded(loaded, key=key, device=self.render_device, threads=self.render_threads)
                ctx.photos = painter_for(loaded, spec, refined)
            ctx.curvature_dir = self.cache_dir / "curvature"  # computed once for this machine's workers
            return ctx

        return self.space_cache.get(key, loader)

    def _view_context(self, t: Claimed, job: JobInfo, space: Space, plan: SpacePlan, view: PlannedView) -> ViewContext:
        """A ViewContext holding the view's pass set: memory LRU, else the store's pass cache, else a render."""
        vk = (t.job_id, t.space_id, t.point, t.view)
        ctx = self.inputs.cached_view(vk)
        if ctx is not None:
            return ctx
        params = job.spec.params
        pkey = job.root_key(passes_key(space.name, t.point, t.view))
        passes = None
        if t.cue != "passes":
            try:
                passes = ViewPasses.from_bytes(self.store.get_bytes(pkey))
            except FileNotFoundError:  # the cache was cleared (job finished, then resumed): render again
                log.info("task %d: no cached pass set at %s; rendering the view again", t.id, pkey)
        if passes is not None:
            ctx = ViewContext(view, params, passes=passes, plan=plan)
        else:
            space_ctx = self._space_context(job, space, plan)
            ctx = ViewContext(view, params, space=space_ctx, plan=plan, render_passes=self._job_passes(job))
            _ = ctx.passes  # render now, so the time is booked to this task
            self.renders += 1
        self.inputs.keep_view(vk, ctx)
        return ctx

    @staticmethod
    def _job_passes(job: JobInfo) -> frozenset[str]:
        """The render passes the job's cues read: the cached pass set holds those only."""
        return render_passes_for(job.spec.cues if job.spec.cues is not None else OUTPUT_CUES)


def default_worker_id(name: str | None = None) -> str:
    """This process's worker id: `name` (the worker's --hostname) plus `-<i>` for pool child i > 0, so it
    stays the same when Celery replaces a recycled child; `host:pid` without a name."""
    if not name:
        return f"{socket.gethostname()}:{os.getpid()}"
    from celery.utils.log import (
        current_process_index,  # here: a local worker of `generate` never imports Celery
    )

    index = current_process_index(base=0)  # pool child 0, 1, ...; None outside a pool
    return f"{name}-{index}" if index else name
