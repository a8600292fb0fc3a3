"""Send again the queued tasks whose Celery message sits where no live worker will ever run it.

A worker reserves (prefetches) a message before its process claims the task; Redis keeps a reserved,
unacknowledged message out of every queue until the broker's visibility timeout (an hour) runs out. A worker
killed while it holds one (reserved, or mid-claim) leaves its task `queued` in the database with no message
anyone will deliver. Redis does not record which consumer holds which message, so recovery does not depend on
knowing it. A queued task of a running job is sent again when

- a worker consuming its queue was declared dead (no heartbeat for `dead_after_s`) and the task was queued
  before that moment: the dead worker may have held its message. Sending moves `queued_at` to now, which is
  after the declaration, so one death sends a task again once, not on every pass. A worker restarted under
  the same name (a container restarted in place keeps its hostname and pid) beats again before it could be
  declared dead; its new run's start, the row's `started_at` moving on between two passes, counts as that
  death instead;
- it has been queued longer than `stuck_after_s` while a live worker consuming its queue sat idle (no current
  task, nothing finished) across two reaper passes with a heartbeat in between: a message waiting in the queue
  would have reached that worker, so its message is held elsewhere or lost.

A duplicate is harmless: a worker claims only a task still `queued`, and only the claiming worker can complete
it (the state table refuses a second completion), while output keys are deterministic.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import ColumnElement, and_, false, or_, select, update
from sqlalchemy.orm import Session

from services.core.celery_config import RENDER_CUES
from services.core.db.models import Job, JobState, Task, TaskState, Worker, utcnow
from services.core.settings import Settings
from services.scheduler.transport import Transport

log = logging.getLogger(__name__)

RESEND_BATCH = 10_000  # tasks sent again per pass at most


@dataclass(frozen=True)
class WorkerSeen:
    """One observation of a worker row by the reaper."""

    last_heartbeat: datetime
    current_task_id: int | None
    tasks_done: int
    started_at: datetime


@dataclass
class IdleWatch:
    """Remembers each worker's row from the previous pass, to tell a worker idle for a while from one between
    tasks, and a new run of a worker from the one before it."""

    seen: dict[str, WorkerSeen] = field(default_factory=dict)

    def restarted_at(self, worker_id: str, now_seen: WorkerSeen) -> datetime | None:
        """The start of a new run of this worker since the previous observation (the previous run died), if
        any."""
        before = self.seen.get(worker_id)
        return now_seen.started_at if before is not None and now_seen.started_at > before.started_at else None

    def idle(self, worker_id: str, now_seen: WorkerSeen) -> bool:
        """True when this and the previous observation both show no task, nothing finished in between, and a
        heartbeat in between (so the row is not merely stale); records the observation."""
        before = self.seen.get(worker_id)
        self.seen[worker_id] = now_seen
        return (
            before is not None
            and now_seen.current_task_id is None
            and before.current_task_id is None
            and now_seen.tasks_done == before.tasks_done
            and now_seen.last_heartbeat > before.last_heartbeat
        )

    def forget_except(self, worker_ids: Iterable[str]) -> None:
        """Drop observations of workers whose rows are gone."""
        keep = set(worker_ids)
        for wid in [w for w in self.seen if w not in keep]:
            del self.seen[wid]


@dataclass
class ResendResult:
    """Tasks sent again by one pass, by reason."""

    after_death: int = 0
    idle_consumers: int = 0
    send_failed: bool = False

    @property
    def total(self) -> int:
        """All tasks sent again."""
        return self.after_death + self.idle_consumers


def _queue_cues(queue: str, settings: Settings) -> ColumnElement[bool]:
    """SQL condition: the task's cue is consumed from `queue`."""
    render = list(RENDER_CUES)
    parts = []
    if queue == settings.queue_render:
        parts.append(Task.cue.in_(render))
    if queue == settings.queue_derive:
        parts.append(Task.cue.not_in(render))
    return or_(*parts) if parts else false()


def _cutoffs(
    session: Session, settings: Settings, watch: IdleWatch, now: datetime, dead_after_s: float,
) -> tuple[dict[str, datetime], set[str]]:
    """Per queue, the moment its most recently dead consumer was declared dead (within the lease), and the
    queues with an idle live consumer."""
    # older deaths: the lost-message rule ran
    horizon = now - timedelta(seconds=dead_after_s + settings.lease_s)
    rows = session.execute(
        select(Worker.id, Worker.queues, Worker.last_heartbeat, Worker.current_task_id, Worker.tasks_done,
               Worker.started_at)
        .where(Worker.last_heartbeat > horizon)
    ).all()
    dead_at: dict[str, datetime] = {}
    idle: set[str] = set()
    for row in rows:
        queues = [str(q) for q in (row.queues or [])]
        declared = row.last_heartbeat + timedelta(seconds=dead_after_s)
        if declared > now:  # alive, unless this is a new run of a worker whose previous run died
            seen = WorkerSeen(
                row.last_heartbeat, row.current_task_id, int(row.tasks_done or 0), row.started_at
            )
            restarted = watch.restarted_at(str(row.id), seen)
            if watch.idle(str(row.id), seen):
                idle.update(queues)
            if restarted is None:
                continue
            declared = restarted
        for q in queues:
            dead_at[q] = max(dead_at.get(q, declared), declared)
    watch.forget_except(str(r.id) for r in rows)
    return dead_at, idle


def resend_stuck(
    session: Session, transport: Transport, settings: Settings, watch: IdleWatch, *,
    dead_after_s: float, stuck_after_s: float, now: datetime | None = None,
) -> ResendResult:
    """One pass: move `queued_at` of stuck queued tasks to now, commit, then send them again. Returns the
    counts."""
    now = now or utcnow()
    res = ResendResult()
    dead_at, idle = _cutoffs(session, settings, watch, now, dead_after_s)
    stuck_cutoff = now - timedelta(seconds=stuck_after_s)
    reasons: list[tuple[str, ColumnElement[bool]]] = []
    for queue, declared in dead_at.items():
        reasons.append(("after_death", and_(_queue_cues(queue, settings), Task.queued_at < declared)))
    for queue in idle:
        reasons.append(("idle_consumers", and_(_queue_cues(queue, settings), Task.queued_at < stuck_cutoff)))
    if not reasons:
        session.rollback()
        return res
    picked: list[tuple[int, str]] = []
    for reason, cond in reasons:
        rows = session.execute(
            update(Task)
            .where(
                Task.state == TaskState.QUEUED, cond,
                Task.job_id.in_(select(Job.id).where(Job.state == JobState.RUNNING)),
                Task.id.in_(
                    select(Task.id).where(Task.state == TaskState.QUEUED, cond).order_by(Task.id)
                    .limit(RESEND_BATCH - len(picked))
                ),
            )
            .values(queued_at=now)
            .returning(Task.id, Task.cue)
            .execution_options(synchronize_session=False)
        ).all()
        picked.extend((int(r.id), str(r.cue)) for r in rows)
        setattr(res, reason, getattr(res, reason) + len(rows))
        if len(picked) >= RESEND_BATCH:
            break
    session.commit()  # the new queued_at is durable before the messages exist, as in dispatch
    if not picked:
        return res
    try:
        transport.send(sorted(picked))
    except Exception:  # they stay queued: the next idle-consumer pass or the lost-message rule sends them
        res.send_failed = True
        log.exception("sending %d stuck tasks again failed", len(picked))
        return res
    log.info("re-sent %d queued tasks whose message a dead worker may hold and %d stuck behind idle workers",
             res.after_death, res.idle_consumers)
    return res
