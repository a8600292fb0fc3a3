"""Compute a batch of claimed tasks, store their files together and record what became of each.

The files of a batch go to the store in one call (store.put_many: one wait for the disk or the network a
view), then every stored task is recorded done in one statement (services.worker.run.claim). A failure is
retried or failed for good (services.worker.run.failure_policy), a task whose input failed in the batch is
handed back to pending unrun, and a store that fails (full, S3 5xx) holds the job instead, the tasks'
attempts not counted (TaskLedger.hold_for_storage).
"""

from __future__ import annotations

import time
from typing import Protocol

from services.core.domain.cues import CATALOG
from services.core.settings import Settings
from services.core.storage import ObjectInfo, ObjectStore, storage_outage
from services.worker.inputs.caches import TaskInputs
from services.worker.run.claim import Claimed, Outcome, TaskLedger
from services.worker.run.stop_signal import reraise_stop

Recorded = tuple[Claimed, str, ObjectInfo, float]  # a stored task: its key, object and seconds


class Producer(Protocol):
    """What computes a task's file (the runner: tests and benches replace its methods)."""

    def make(self, t: Claimed) -> tuple[str, bytes]: ...

    def execute(self, t: Claimed) -> tuple[str, ObjectInfo]: ...


class BatchResults:
    """Stores and records the results of one worker's batches of claimed tasks."""

    def __init__(self, producer: Producer, store: ObjectStore, ledger: TaskLedger, inputs: TaskInputs,
                 settings: Settings) -> None:
        self.producer = producer
        self.store = store
        self.ledger = ledger
        self.inputs = inputs
        self.settings = settings

    def record_failure(self, t: Claimed, exc: Exception, t0: float) -> Outcome:
        """Retry or fail the task, or hold its job when the store failed rather than the task."""
        outage = storage_outage(exc)
        if outage is not None:  # the store failed, not the task: it waits for the store, uncounted
            return self.ledger.hold_for_storage([t], outage)[0]
        max_attempts = self.inputs.max_attempts(t.job_id, self.settings.max_attempts)
        return self.ledger.record_failure(t, exc, time.perf_counter() - t0, max_attempts)

    def compute(self, claimed: list[Claimed], t0: float) -> tuple[list[Recorded], dict[int, Outcome]]:
        """Compute each claimed task in order, then store their files together (store.put_many); failures
        are recorded one by one, and a task an input of which failed here is handed back to pending unrun (the
        DAG's rule: a cue is queued when its inputs exist). Returns the stored tasks, and the Outcomes of the
        others by task id. A task's seconds are its computation's plus its share (by bytes) of the store's."""
        made: list[tuple[Claimed, str, bytes, float]] = []
        t_batch = t0
        try:
            for t in claimed:
                key, data = self.producer.make(t)
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

    def _compute_one_by_one(
        self, claimed: list[Claimed], t0: float,
    ) -> tuple[list[Recorded], dict[int, Outcome]]:
        """compute's path when a task of the batch failed: compute and store each task on its own."""
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
                key, info = self.producer.execute(t)
            except Exception as exc:
                reraise_stop(exc)
                failed[t.id] = self.record_failure(t, exc, t0)
                lost.add(t.cue)
                failed_cues.append(t.cue)
            else:
                done.append((t, key, info, time.perf_counter() - t0))
            t0 = time.perf_counter()
        if unrun:
            why = f"handed back to pending unrun: {', '.join(failed_cues)} failed in its view batch"
            failed.update((o.task_id, o) for o in self.ledger.hand_back(unrun, why))
        return done, failed

    def record(self, order: list[Claimed], done: list[Recorded], failed: dict[int, Outcome]) -> list[Outcome]:
        """Record the stored tasks done together (ledger.record_done_many); every Outcome, in `order`."""
        recorded = {o.task_id: o for o in self.ledger.record_done_many(done)} if done else {}
        return [failed.get(t.id) or recorded[t.id] for t in order]
