"""Recent throughput per job, measured from successive counter readings kept in memory.

Progress never counts task rows; the rate comes from how the finished count moved over the last minute of
readings (GET /jobs polls and the SSE stream both feed it), so an ETA follows the job's current pace.
"""

from __future__ import annotations

import threading
import time
from collections import deque


class RateTracker:
    """Recent finish rate per job from successive counter readings (thread-safe, bounded memory)."""

    def __init__(self, window_s: float = 60.0, min_span_s: float = 2.0, max_jobs: int = 10_000):
        self.window_s = window_s
        self.min_span_s = min_span_s
        self.max_jobs = max_jobs
        self._samples: dict[int, deque[tuple[float, int, int]]] = {}
        self._lock = threading.Lock()

    def observe(
        self, job_id: int, finished: int, labels: int, now: float | None = None
    ) -> tuple[float, float] | None:
        """Record a reading (monotonic seconds); return (tasks/s, labels/s) over the window, or None if too
        short."""
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._samples.get(job_id)
            if q is None:
                if len(self._samples) >= self.max_jobs:
                    self._evict(now)
                q = self._samples[job_id] = deque()
            if not q or now - q[-1][0] >= 0.2 or q[-1][1] != finished:
                q.append((now, finished, labels))
            # Keep one sample older than the window so the rate always spans the whole window.
            while len(q) > 2 and now - q[1][0] >= self.window_s:
                q.popleft()
            t0, n0, l0 = q[0]
            t1, n1, l1 = q[-1]
            if t1 - t0 < self.min_span_s:
                return None
            if n1 < n0:  # counters went down (retry of failed tasks): restart the window
                q.clear()
                q.append((t1, n1, l1))
                return None
            return (n1 - n0) / (t1 - t0), max(0, l1 - l0) / (t1 - t0)

    def idle_s(self, job_id: int, now: float | None = None) -> float:
        """Seconds since the job's finished count last changed, as far as the kept readings tell (0 if
        unknown)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._samples.get(job_id)
            if not q:
                return 0.0
            since = q[0][0]
            for k in range(len(q) - 1, 0, -1):
                if q[k - 1][1] != q[k][1]:
                    since = q[k][0]
                    break
            return max(0.0, now - since)

    def _evict(self, now: float) -> None:
        stale = [j for j, q in self._samples.items() if not q or now - q[-1][0] > self.window_s]
        for j in stale or list(self._samples)[: len(self._samples) // 2]:
            del self._samples[j]
