"""Worker heartbeat (execution contract: Reaper): a thread that keeps the worker's row fresh every few seconds
and extends the lease of the task it is running before the lease runs out.

The `worker` row (id: the worker's name, or host:pid) carries host, queues, last heartbeat, current task,
tasks done, labels per cue and labels/s over the last minute; the dashboard reads it. A worker that stops
beating (kill -9, lost node) is declared dead after OMNIDATA_HEARTBEAT_TIMEOUT_S, and the scheduler's reaper
gives its task to another worker then, without waiting for the task's lease to run out.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from datetime import timedelta

from sqlalchemy import update
from sqlalchemy.orm import Session

from services.core.db.bulk import upsert
from services.core.db.models import Task, TaskState, Worker, utcnow

log = logging.getLogger(__name__)

HEARTBEAT_INTERVAL_S = 5.0
RATE_WINDOW_S = 60.0  # labels/s is measured over this trailing window


def heartbeat_interval(lease_s: float) -> float:
    """Seconds between beats: 5 s, or a third of `lease_s` (the lease or heartbeat timeout) when shorter, >=
    0.5 s."""
    return max(0.5, min(HEARTBEAT_INTERVAL_S, lease_s / 3.0))


class Heartbeat:
    """Beats for one worker process: `start()` runs `beat()` in a daemon thread every `interval_s` seconds."""

    def __init__(
        self,
        sessionmaker: Callable[[], Session],
        worker_id: str,
        *,
        queues: Sequence[str] = (),
        lease_s: float = 300.0,
        interval_s: float | None = None,
        host: str | None = None,
    ) -> None:
        self._sessionmaker = sessionmaker
        self.worker_id = worker_id
        self.host = host or socket.gethostname()
        self.queues = list(queues)
        self.lease_s = float(lease_s)
        self.interval_s = heartbeat_interval(lease_s) if interval_s is None else float(interval_s)
        # The worker row says it is alive every beat (the reaper's heartbeat timeout); the task row, written
        # far less often, only needs its lease pushed before it runs out: a third of the way in, not every 5
        # s.
        self.extend_after_s = self.lease_s / 3.0
        self._leased_at = 0.0  # monotonic time of the current task's claim or last lease extension
        self._lock = threading.Lock()
        self._beat_lock = threading.Lock()
        self._current: int | None = None
        self._batch: tuple[int, ...] = ()
        self._tasks_done = 0
        self._labels: dict[str, int] = {}
        self._recent: deque[tuple[float, int]] = deque()  # (monotonic time, labels) of recent tasks
        # the row's counts when this process took it
        self._inherited: tuple[int, dict[str, int]] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.beats = 0
        self.last_error: str | None = None

    # ------------------------------------------------------------------ called by the runner

    def set_current(self, task_id: int | None, batch: Sequence[int] = ()) -> None:
        """The task this worker has just claimed with a full lease, and the other tasks of its view batch
        (beats extend the leases of all of them), or None when idle."""
        with self._lock:
            if task_id != self._current:
                self._leased_at = time.monotonic()
            self._current = task_id
            self._batch = tuple(batch) if task_id is not None else ()

    def record_done(self, cue: str, labels: int = 1) -> None:
        """Count a finished task and the labels (output files) it produced."""
        now = time.monotonic()
        with self._lock:
            self._tasks_done += 1
            if labels:
                self._labels[cue] = self._labels.get(cue, 0) + labels
                self._recent.append((now, labels))
            self._trim(now)

    @property
    def tasks_done(self) -> int:
        """Tasks this worker finished since it started."""
        with self._lock:
            return self._tasks_done

    def labels_per_s(self) -> float:
        """Labels produced per second over the trailing window (or since the first label, if shorter)."""
        now = time.monotonic()
        with self._lock:
            self._trim(now)
            if not self._recent:
                return 0.0
            span = max(now - self._recent[0][0], 1.0)
            return sum(n for _, n in self._recent) / min(span, RATE_WINDOW_S)

    def _trim(self, now: float) -> None:
        while self._recent and now - self._recent[0][0] > RATE_WINDOW_S:
            self._recent.popleft()

    # ------------------------------------------------------------------ the beat

    def register(self) -> None:
        """Beat as a new run of this worker: the row's `started_at` becomes now. The scheduler takes a start
        that moved on for the death of the run before (services.scheduler.resend): a worker restarted under
        its name beats again before it could be declared dead."""
        with self._beat_lock:
            self._beat(new_run=True)

    def beat(self) -> None:
        """Upsert the worker row (one statement) and, once `extend_after_s` has passed since the claim or the
        last extension, extend the current task's lease (only while it is still ours and running)."""
        # the thread's beat and a direct call (stop, tests) land in the order they were made
        with self._beat_lock:
            self._beat()

    def _beat(self, *, new_run: bool = False) -> None:
        rate = self.labels_per_s()
        with self._lock:
            current, held, done, labels = (
                self._current, (self._current, *self._batch), self._tasks_done, dict(self._labels),
            )
            extend = current is not None and time.monotonic() - self._leased_at >= self.extend_after_s
        now = utcnow()
        with self._sessionmaker() as session, session.begin():
            if self._inherited is None:
                # A named worker's row outlives its child processes (recycling): carry on its counts.
                prev = session.get(Worker, self.worker_id)
                self._inherited = (
                    (int(prev.tasks_done or 0), dict(prev.labels or {})) if prev is not None else (0, {})
                )
            base_done, base_labels = self._inherited
            row = {
                "id": self.worker_id, "host": self.host, "queues": self.queues, "started_at": now,
                "last_heartbeat": now, "current_task_id": current, "tasks_done": base_done + done,
                "labels_per_s": rate,
                "labels": {
                    cue: int(base_labels.get(cue, 0)) + labels.get(cue, 0) for cue in {*base_labels, *labels}
                },
            }
            upsert(session, Worker, row, key=["id"], insert_only=[] if new_run else ["started_at"])
            if extend:
                # Not a state change (counters untouched): only pushes the deadline of a task we hold.
                session.execute(
                    update(Task)
                    .where(
                        Task.id.in_(held), Task.worker_id == self.worker_id, Task.state == TaskState.RUNNING
                    )
                    .values(lease_until=now + timedelta(seconds=self.lease_s))
                    .execution_options(synchronize_session=False)
                )
        if extend:
            with self._lock:
                self._leased_at = time.monotonic()
        self.beats += 1

    def _try_beat(self) -> None:
        try:
            self.beat()
            self.last_error = None
        except Exception as e:  # a database hiccup must not kill the thread: the next beat retries
            self.last_error = f"{type(e).__name__}: {e}"
            log.warning("heartbeat of %s failed: %s", self.worker_id, self.last_error)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._try_beat()

    def start(self) -> Heartbeat:
        """Beat once, here, then every `interval_s` in a daemon thread (idempotent).

        The first beat is made before returning, so the worker row exists before the caller claims a task, and
        the reaper can take a running task whose worker has no row for a killed worker's."""
        if self._thread is None or not self._thread.is_alive():
            self._stop.clear()
            self._try_beat()
            self._thread = threading.Thread(target=self._run, name=f"heartbeat-{self.worker_id}", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread and mark the worker idle (best effort)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.set_current(None)
        try:
            self.beat()
        except Exception:
            pass


def expire_leases(sessionmaker: Callable[[], Session], worker_ids: Sequence[str]) -> int:
    """Let the reaper take back the tasks of workers that died (their leases end now); returns how many."""
    if not worker_ids:
        return 0
    with sessionmaker() as session:
        res = session.execute(
            update(Task).where(Task.state == TaskState.RUNNING, Task.worker_id.in_(list(worker_ids)))
            .values(lease_until=utcnow() - timedelta(seconds=1)).execution_options(synchronize_session=False)
        )
        session.commit()
        return int(res.rowcount or 0)  # type: ignore[attr-defined]


def live_holder(sessionmaker: Callable[[], Session], worker_id: str, *, within_s: float) -> str | None:
    """The host of another machine's worker beating under `worker_id` in the last `within_s` seconds, if any.

    Two workers must not share a name: each new process of a name ends the leases its predecessor held.
    A row of this host is not counted: it is this worker's own previous run.
    """
    with sessionmaker() as session:
        row = session.get(Worker, worker_id)
        if row is None or row.host == socket.gethostname():
            return None
        age = (utcnow() - row.last_heartbeat).total_seconds()
        return row.host if age < within_s else None
