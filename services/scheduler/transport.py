"""How dispatched tasks reach workers: a small Protocol and the in-process transports (Celery's is in
services.scheduler.celery_transport, so an embedded run never imports Celery).

The scheduler marks tasks queued and commits before it calls `send`, so a send that fails or is lost
leaves tasks that the reaper (or the dispatcher's own rollback) puts back to pending; a duplicate
message is harmless because a worker only claims a task that is still queued.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from services.core.celery_config import RENDER_CUES


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
    """Sends task ids into a queue (a multiprocessing queue of the embedded mode's local workers); with
    `render_q`, the tasks that render go there instead (the embedded mode's render queue)."""

    def __init__(self, q: TaskIdQueue, render_q: TaskIdQueue | None = None) -> None:
        self.q = q
        self.render_q = render_q if render_q is not None else q
        self.sent = 0

    def send(self, batch: Sequence[tuple[int, str]]) -> None:
        """Put one task id per message on its queue."""
        for task_id, cue in batch:
            (self.render_q if cue in RENDER_CUES else self.q).put(int(task_id))
        self.sent += len(batch)
