"""TaskRunner: run one task of the execution contract.

    runner = TaskRunner(sessionmaker, store, settings, worker_id)
    outcome = runner.run(task_id)

1. Claim the task (services.worker.run.claim: queued -> running, or why not).
2. Load the job spec, the space (kept loaded between tasks: SpaceCache) and the plan JSON
   (services.worker.inputs.caches; services.worker.run.making computes a task's bytes from them).
3. Compute: the `passes` task renders the view once into this process's memory; every other cue is derived
   from that pass set, read from this process's memory LRU or the store's pass cache (.npz, written only when
   a task of the view may need it after the view batch below), and rendered again only if the cache is gone
   (e.g. after a resume of a finished job).
4. Write the objects atomically to their deterministic keys, a batch's together (store.put_many: one wait for
   the disk or the network a view), then record them done (services.worker.run.results and
   services.worker.run.claim).
   View batch (settings.worker_batch_views): the worker that rendered a view's `passes` claims, in one
   statement, the rest of that view's tasks, pending or queued (every DAG level: all their inputs are cues of
   the view, computed in memory by its ViewContext in topological order), derives and stores each, and records
   them all done, `passes` included, in one statement: ~3 statements a view instead of ~2 per task. When the
   batch made every task of the view that reads the pass set, the pass set is never stored (`passes` is
   recorded with size 0, no sha256). A derived cue's task (a view the batch did not take whole: rendered by a
   renderer of `generate --render-workers`, which stores the pass set and leaves the view to the others
   (hand_off_views); a retry; a resume) claims its view's queued tasks alike, and when it reads the pass set
   (so the pass set is done) the pending ones too: the pass set, read once, gives every cue of the view, where
   queued-only took one batch and one read of the pass set per DAG level.
   Each task keeps its row; a pending task claimed so gets no message, a queued one's message is skipped when
   it comes (a read, no claim). A task whose input failed in the batch, or runs on another worker, is handed
   back to pending unrun. A batch whose worker dies stays `running` under its lease (the beats extend all of
   it): the reaper re-queues every task of it.
5. Failure: retry after a backoff or fail for good, and keep a failing worker off the job
   (services.worker.run.failure_policy); a store that fails (full, S3 5xx) holds the job instead, its tasks'
   attempts not counted (TaskLedger.hold_for_storage), until the scheduler sees the store take writes again.

Bytes, not files, flow through here; all geometry is in the plan (world metres, OpenCV camera axes).
"""

from __future__ import annotations

import os
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from sqlalchemy.orm import Session

from services.core.settings import Settings
from services.core.storage import ObjectInfo, ObjectStore
from services.worker.inputs.caches import VIEW_CACHE_MEMORY_FRACTION, TaskInputs
from services.worker.inputs.space_cache import SpaceCache, should_recycle
from services.worker.run.claim import DB_RETRY_S, Claimed, Outcome, TaskLedger
from services.worker.run.heartbeat import Heartbeat
from services.worker.run.making import TaskMaker, needs_passes
from services.worker.run.pass_handoff import PassSets, StoredPassSets
from services.worker.run.results import BatchResults
from services.worker.run.stop_signal import reraise_stop

BATCHED_MEMORY = 4096  # task ids of recent view batches remembered, so their late messages skip the claim


class TaskRunner:
    """Runs tasks for one worker process (`worker_id`, e.g. host:pid); not thread-safe: one task at a time.

    It decides what runs together (a task, a view batch); `maker` computes a task's bytes and `results`
    stores and records them."""

    def __init__(
        self,
        sessionmaker: Callable[[], Session],
        store: ObjectStore,
        settings: Settings,
        worker_id: str,
        *,
        heartbeat: Heartbeat | None = None,
        cache_dir: str | Path | None = None,
        curvature_dir: Path | None = None,
        render_threads: int | None = None,
        render_device: str | None = None,
        db_retry_s: float = DB_RETRY_S,
        hand_off_views: bool = False,
        pass_sets: PassSets | None = None,
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
        # A renderer of `generate --render-workers`: a `passes` task stores its pass set for the workers that
        # only derive, instead of deriving the view itself (a view batch).
        self.hand_off_views = hand_off_views
        # where a handed-off pass set goes (`generate`: raw files, services.worker.run.pass_handoff)
        self.pass_sets = pass_sets or StoredPassSets(store)
        self.ledger = TaskLedger(sessionmaker, worker_id, settings.lease_s, db_retry_s)
        self.inputs = TaskInputs(sessionmaker, store, self.ledger.db,
                                 int(VIEW_CACHE_MEMORY_FRACTION * settings.worker_max_memory_mb * 2**20))
        self.maker = TaskMaker(store, self.inputs, self.cache_dir, render_device=self.render_device,
                               render_threads=self.render_threads, pass_sets=self.pass_sets,
                               curvature_dir=curvature_dir)
        self.results = BatchResults(self, store, self.ledger, self.inputs, settings)
        # Messages run (a view batch is one, like Celery's worker_max_tasks_per_child counts it): the recycle
        # count.
        self.tasks_run = 0
        self.batched: deque[int] = deque(maxlen=BATCHED_MEMORY)  # ids this process ran in view batches lately

    @property
    def renders(self) -> int:
        """Pass sets rendered by this process (one per view, unless a cache was lost)."""
        return self.maker.renders

    @property
    def space_cache(self) -> SpaceCache:
        """The space this process keeps loaded between tasks."""
        return self.maker.space_cache

    def run(self, task_id: int) -> Outcome:
        """Claim and run one task, and with it the rest of its view (a view batch, when
        settings.worker_batch_views): after a `passes` task, the view's pending and queued tasks; after a
        derived cue's, the view's queued ones, and pending ones too when it reads the pass set. Never raises
        for task failures (they are recorded), only TransientError. The returned Outcome is the message's
        task's; `batch` holds the others'."""
        t0 = time.perf_counter()
        if task_id in self.batched and self.ledger.is_settled(task_id):
            # Its message came after a view batch of ours ran it: no claim attempt (no write lock) for a
            # no-op.
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
                outcomes = (
                    self._hand_off_view(claimed, t0) if self.hand_off_views else self._run_view(claimed, t0)
                )
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
        """The rest of the claimed task's view (ledger.claim_view_rest), remembered, and leased by the
        beats."""
        rest, elsewhere = self.ledger.claim_view_rest(claimed, with_pending=with_pending)
        self.batched.extend(c.id for c in rest)
        if self.heartbeat is not None:
            self.heartbeat.set_current(claimed.id, [c.id for c in rest])
        return rest, elsewhere

    def _run_view(self, passes: Claimed, t0: float) -> list[Outcome]:
        """The whole view on this worker: render its pass set (the `passes` task) into memory, claim the rest
        of the view in one statement, derive it, and record everything done in one statement. The pass set is
        stored only when a task of the view that reads it may run later (not claimed, failed or handed back):
        otherwise nobody reads it (a re-run after a resume renders again), and `passes` is recorded with size
        0 and no sha256, and the view's context leaves the memory LRU at once: kept, the LRU's budget held ~60
        views' arrays, so every view wrote into fresh pages (1.6 GB of page faults a 66-view run, ~30 ms a
        view). A failed render is recorded alone: the rest of the view stays pending."""
        try:
            key = self.render_view(passes)
        except Exception as exc:
            reraise_stop(exc)
            return [self.results.record_failure(passes, exc, t0)]
        render_s = time.perf_counter() - t0
        rest, elsewhere = self._claim_rest(passes, with_pending=True)
        done, failed = self.results.compute(rest, time.perf_counter())
        info = ObjectInfo(key, 0, None)
        t1 = time.perf_counter()
        if elsewhere or len(done) < len(rest):
            try:
                key, info = self.execute(passes)  # serialised from the pass set in memory, and stored
            except Exception as exc:
                reraise_stop(exc)
                failed[passes.id] = self.results.record_failure(passes, exc, t1 - render_s)
        if passes.id not in failed:
            done.insert(0, (passes, key, info, render_s + time.perf_counter() - t1))
        # nothing of the view is left to run: free its arrays for the next view
        if not elsewhere and not failed:
            self.inputs.forget_view((passes.job_id, passes.space_id, passes.point, passes.view))
        return self.results.record([passes, *rest], done, failed)

    def _hand_off_view(self, passes: Claimed, t0: float) -> list[Outcome]:
        """Render the view and store its pass set (in pass_store) for whoever derives it; its arrays leave
        this process at once."""
        try:
            key = self.render_view(passes)
            ctx = self.inputs.cached_view((passes.job_id, passes.space_id, passes.point, passes.view))
            assert ctx is not None  # render_view keeps it
            info = self.pass_sets.put(key, ctx.passes)
        except Exception as exc:
            reraise_stop(exc)
            outcomes = [self.results.record_failure(passes, exc, t0)]
        else:
            outcomes = self.results.record([passes], [(passes, key, info, time.perf_counter() - t0)], {})
        self.inputs.forget_view((passes.job_id, passes.space_id, passes.point, passes.view))
        return outcomes

    def _run_derived(self, claimed: Claimed, t0: float) -> list[Outcome]:
        """A derived cue's task and the rest of its view this worker could claim: the queued tasks, and the
        pending ones too when it reads the pass set (module docstring). Once nothing of the view reads the
        pass set any more, its arrays leave the memory LRU (see _run_view)."""
        reads = needs_passes(claimed.cue)
        rest, elsewhere = self._claim_rest(claimed, with_pending=reads)
        outcomes = self._run_claimed([claimed, *rest], t0)
        # elsewhere also when none claimed
        if reads and not elsewhere and all(o.status == "done" for o in outcomes):
            self.inputs.forget_view((claimed.job_id, claimed.space_id, claimed.point, claimed.view))
        return outcomes

    def _run_claimed(self, claimed: list[Claimed], t0: float) -> list[Outcome]:
        """Compute, store and record claimed tasks (the first one's time counts from `t0`, its claim)."""
        done, failed = self.results.compute(claimed, t0)
        return self.results.record(claimed, done, failed)

    def should_recycle(self) -> bool:
        """True when this process should exit after the task: RSS above worker_max_memory_mb or
        worker_max_tasks messages run. A view batch counts once: counted by its ~18 tasks, a 66-view
        `generate` restarted its worker twice, each restart paying imports, the space load and Cycles' first
        render again (~3
        CPU-s)."""
        return self.tasks_run >= self.settings.worker_max_tasks or should_recycle(
            self.settings.worker_max_memory_mb
        )

    def close(self) -> None:
        """Free the loaded space and cached views."""
        self.maker.close()

    def execute(self, t: Claimed) -> tuple[str, ObjectInfo]:
        """Compute the task's bytes and store them at the deterministic key; returns (key, ObjectInfo)."""
        key, data = self.make(t)
        return key, self.store.put_bytes(key, data)

    def make(self, t: Claimed) -> tuple[str, bytes]:
        """The task's deterministic key and file bytes (nothing stored)."""
        return self.maker.make(t)

    def render_view(self, t: Claimed) -> str:
        """Render the view of a `passes` task into this process's memory (nothing stored); its pass set's
        key."""
        return self.maker.render_view(t)


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
