"""How dispatched tasks reach workers: a small Protocol and the in-process transports (Celery's is in
services.scheduler.celery_transport, so an embedded run never imports Celery).

The scheduler marks tasks queued and commits before it calls `send`, so a send that fails or is lost
leaves tasks that the reaper (or the dispatcher's own rollback) puts back to pending; a duplicate
message is harmless because a worker only claims a task that is still queued.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol


class Transport(Protocol):
    """Delivers (task_id, cue) pairs to workers; raises when it could not."""

    def send(self, batch: Sequence[tuple[int, str]]) -> None:
        """Send one message per task."""
        ...


class NullTransport:
    """Sends nothing and remembers what it was given (tests, dry runs)."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, str]] = []

    def send(self, batch: Sequence[tuple[int, str]]) -> None:
        """Record the batch."""
        self.sent.extend((int(i), str(c)) for i, c in batch)


class TaskIdQueue(Protocol):
    """A queue of task ids: a multiprocessing queue (embedded workers) or queue.Queue (tests)."""

    def put(self, item: int, /) -> None: ...


class QueueTransport:
    """Sends task ids into a queue (a multiprocessing queue of the embedded mode's local workers)."""

    def __init__(self, q: TaskIdQueue) -> None:
        self.q = q
        self.sent = 0

    def send(self, batch: Sequence[tuple[int, str]]) -> None:
        """Put one task id per message on the queue."""
        for task_id, _cue in batch:
            self.q.put(int(task_id))
        self.sent += len(batch)
