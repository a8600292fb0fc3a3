"""One database read per tenant and poll interval, shared by all of that tenant's event streams.

Every stream used to read its jobs and counters itself, twice a second: 200 streams were 400 reads a second in
the API process, whose Python work (under the GIL) delayed everything else it served, /health included.
Streams that follow the same jobs (the same tenant, and the same job or all of them) now share a read younger
than `max_age_s` (half the poll interval, so an event is at most that much later), and each stream only
compares it with what it has already sent.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from sqlalchemy.orm import Session

from services.api.jobs.service import RateTracker
from services.api.progress.service import FinalCounters, JobsRead, Snapshot, diff_jobs, read_jobs
from services.core.domain.json_types import JSONObject

MAX_ENTRIES = 10_000  # (tenant, job) reads kept at most; the oldest are dropped beyond


class SharedPolls:
    """Reads shared by streams of the same (tenant, followed job); safe to call from many threads."""

    def __init__(self, sessionmaker: Callable[[], Session], max_age_s: float) -> None:
        self.sessionmaker = sessionmaker
        self.max_age_s = max_age_s
        self._guard = threading.Lock()
        self._locks: dict[tuple[str, int | None], threading.Lock] = {}
        self._reads: dict[tuple[str, int | None], tuple[float, JobsRead]] = {}
        self._final: dict[tuple[str, int | None], FinalCounters] = {}
        self.reads = 0  # database reads made (for tests and benchmarks)

    def read(self, owner: str, job_id: int | None) -> JobsRead:
        """A read of the tenant's followed jobs no older than max_age_s (made now if there is none)."""
        key = (owner, job_id)
        with self._guard:
            lock = self._locks.setdefault(key, threading.Lock())
        with lock:  # streams of one key wait for one read instead of each making their own
            hit = self._reads.get(key)
            if hit is not None and time.monotonic() - hit[0] < self.max_age_s:
                return hit[1]
            with self.sessionmaker() as session:
                read = read_jobs(session, owner=owner, job_id=job_id, final=self._final.setdefault(key, {}))
            self.reads += 1
            with self._guard:
                self._reads[key] = (time.monotonic(), read)
                if len(self._reads) > MAX_ENTRIES:
                    self._forget_oldest()
            return read

    def poll(
        self, owner: str, job_id: int | None, snap: Snapshot, rates: RateTracker
    ) -> tuple[list[JSONObject], list[int]]:
        """What a stream following (owner, job_id) has not sent yet: changed jobs and deleted ids; updates
        `snap`."""
        return diff_jobs(self.read(owner, job_id), job_id=job_id, snap=snap, rates=rates)

    def _forget_oldest(self) -> None:
        for key, _ in sorted(self._reads.items(), key=lambda kv: kv[1][0])[
            : len(self._reads) - MAX_ENTRIES // 2
        ]:
            self._reads.pop(key, None)
            self._final.pop(key, None)
            self._locks.pop(key, None)
