"""Resuming jobs held for their object store (jobs.hold_for_storage) once it takes writes again.

A worker whose outputs the store would not take (a full folder, S3 answering 5xx) pauses the job; nothing here
retries the tasks one by one. While a job is held, the scheduler probes the store every CHECK_INTERVAL_S (a
small write and delete; a folder also needs room for a few views, LocalStore.probe) and resumes the held jobs
when it passes: the next dispatch pass sends their tasks. The probe runs on a thread of its own, so an S3
endpoint that does not answer (botocore's retries take tens of seconds) never stalls the loop.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, wait

from sqlalchemy.orm import Session, sessionmaker

from services.core.db.jobs import hold_for_storage, release_storage_holds, storage_held_jobs
from services.core.storage import ObjectStore
from services.core.storage.base import io_pool

log = logging.getLogger(__name__)

CHECK_INTERVAL_S = 2.0  # probes a held store this often: work resumes within about this of the store's return
PROBE_WAIT_S = 0.25  # a probe's answer is awaited this long in the tick (a folder's: ms), else next tick


class StoreWatch:
    """Probes the store while a job is held for it; `check()` (each scheduler tick) resumes them once it
    passes."""

    def __init__(self, sessions: sessionmaker[Session], store: ObjectStore,
                 interval_s: float = CHECK_INTERVAL_S) -> None:
        self.sessions = sessions
        self.store = store
        self.interval_s = interval_s
        self._probe: Future[None] | None = None
        self._next = 0.0
        self.last_problem: str | None = None  # the probe's last failure (logged when it changes)

    def check(self) -> list[int]:
        """Ids of the held jobs resumed now ([] most ticks: a query every interval while nothing is held)."""
        if self._probe is None:
            if time.monotonic() < self._next:
                return []
            self._next = time.monotonic() + self.interval_s
            with self.sessions() as s:
                if not storage_held_jobs(s):
                    return []
            self._probe = io_pool().submit(self.store.probe)
            wait([self._probe], timeout=PROBE_WAIT_S)
        if not self._probe.done():
            return []
        probe, self._probe = self._probe, None
        problem = probe.exception()
        if problem is not None:
            if str(problem) != self.last_problem:  # the jobs say the latest reason (e.g. "7.0 MiB left ...")
                log.warning("jobs wait for the object store: %s", problem)
                with self.sessions() as s:
                    for job_id, _ in storage_held_jobs(s):
                        hold_for_storage(s, job_id, str(problem))
                    s.commit()
            self.last_problem = str(problem)
            return []
        with self.sessions() as s:
            resumed = release_storage_holds(s, [job_id for job_id, _ in storage_held_jobs(s)])
            s.commit()
        if resumed:
            log.info("the object store takes writes again: jobs %s resumed", resumed)
        self.last_problem = None
        return resumed
