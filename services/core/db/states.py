"""Where a task or a job changes state: the allowed transitions and the two functions that make them.

Every task state change goes through `transition()`, which moves the tasks with one conditional UPDATE and
adjusts the job's progress counters (`job_counter`) in the same transaction; every job state change goes
through `set_job_state()` (or, for the planner's conditional claim, `check_job_edge()` first). A change not in
the tables below raises IllegalTransition, so a new code path cannot invent an edge silently.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from typing import Any

from sqlalchemy import ColumnElement, Table, update
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from services.core.db.bulk import connection_of
from services.core.db.counters import add_counts
from services.core.db.models import Job, JobState, Task, TaskState

__all__ = [
    "JOB_EDGES", "TASK_EDGES", "IllegalTransition", "JobState", "TaskState", "check_job_edge", "check_task_edge",
    "set_job_state", "transition",
]

# from -> the states a task may go to, and who takes that edge
TASK_EDGES: Mapping[TaskState, frozenset[TaskState]] = {
    # dispatch sends it; dispatch fails it (its pass failed for good); cancel_job
    TaskState.PENDING: frozenset({TaskState.QUEUED, TaskState.FAILED, TaskState.CANCELLED}),
    # dispatch/reaper/worker give it back (paused job, lost message, resume); the worker claims it; cancel_job
    TaskState.QUEUED: frozenset({TaskState.PENDING, TaskState.RUNNING, TaskState.CANCELLED}),
    # reaper/requeue (lease ran out, interrupted); the worker finishes or fails it; reaper of a cancelled job
    TaskState.RUNNING: frozenset({TaskState.PENDING, TaskState.DONE, TaskState.FAILED, TaskState.CANCELLED}),
    TaskState.DONE: frozenset({TaskState.PENDING}),  # resume: its output file is gone
    TaskState.FAILED: frozenset({TaskState.PENDING}),  # retry_failed
    TaskState.CANCELLED: frozenset(),
}

JOB_EDGES: Mapping[JobState, frozenset[JobState]] = {
    JobState.PENDING: frozenset({JobState.PLANNING, JobState.CANCELLED}),
    # planned; planning failed for good; a planner's lease ran out and another claims it (planning again);
    # interrupted embedded run plans again from scratch; cancel_job
    JobState.PLANNING: frozenset({JobState.RUNNING, JobState.FAILED, JobState.PLANNING, JobState.PENDING,
                                  JobState.CANCELLED}),
    JobState.RUNNING: frozenset({JobState.PAUSED, JobState.DONE, JobState.FAILED, JobState.CANCELLED}),
    JobState.PAUSED: frozenset({JobState.RUNNING, JobState.CANCELLED}),
    JobState.DONE: frozenset({JobState.RUNNING}),  # retry_failed, or missing outputs made again
    JobState.FAILED: frozenset({JobState.RUNNING}),
    JobState.CANCELLED: frozenset(),
}

IN_CHUNK = 5_000  # ids per UPDATE ... WHERE id IN (...): below SQLite's and psycopg's parameter limits


class IllegalTransition(ValueError):
    """A state change that the transition tables do not allow."""


def check_task_edge(from_state: str, to_state: str) -> tuple[TaskState, TaskState]:
    """The two states as TaskState; IllegalTransition unless from -> to is an edge of TASK_EDGES."""
    a, b = TaskState(from_state), TaskState(to_state)
    if b not in TASK_EDGES[a]:
        raise IllegalTransition(f"task transition from {a.value!r} to {b.value!r} is not allowed")
    return a, b


def check_job_edge(from_state: str, to_state: str) -> tuple[JobState, JobState]:
    """The two states as JobState; IllegalTransition unless from -> to is an edge of JOB_EDGES."""
    a, b = JobState(from_state), JobState(to_state)
    if b not in JOB_EDGES[a]:
        raise IllegalTransition(f"job transition from {a.value!r} to {b.value!r} is not allowed")
    return a, b


def transition(
    session: Session | Connection,
    *,
    job_id: int,
    from_state: str,
    to_state: str,
    task_ids: Iterable[int] | None = None,
    where: Iterable[ColumnElement[bool]] = (),
    **values: Any,
) -> list[tuple[int, str]]:
    """Move the job's tasks in `from_state` to `to_state` and adjust the counters in the same transaction.

    `task_ids` limits the move to those tasks (None: every task of the job in `from_state`); `where` adds
    conditions (e.g. the worker still holds it); `values` are further columns to set (values or SQL
    expressions, e.g. attempts=Task.attempts + 1). Tasks not in `from_state` are left alone, which makes
    racing transitions safe: only the (id, cue) pairs returned were moved, and only those are counted.
    Task objects already loaded in a Session are not refreshed (reload with populate_existing=True).
    """
    src, dst = check_task_edge(from_state, to_state)
    conn = connection_of(session)
    t = Task.__table__
    assert isinstance(t, Table)
    conds = [t.c.job_id == job_id, t.c.state == src.value, *where]
    stmt = update(t).values(state=dst.value, **values).returning(t.c.id, t.c.cue)
    moved: list[tuple[int, str]] = []
    if task_ids is None:
        moved.extend((int(r[0]), str(r[1])) for r in conn.execute(stmt.where(*conds)))
    else:
        ids = list(dict.fromkeys(int(i) for i in task_ids))
        for start in range(0, len(ids), IN_CHUNK):
            chunk = ids[start : start + IN_CHUNK]
            moved.extend((int(r[0]), str(r[1])) for r in conn.execute(stmt.where(t.c.id.in_(chunk), *conds)))
    per_cue = Counter(cue for _, cue in moved)
    deltas: dict[tuple[str, str], int] = {}
    for cue, k in per_cue.items():
        deltas[(cue, src.value)] = -k
        deltas[(cue, dst.value)] = k
    add_counts(conn, job_id, deltas)
    return moved


def set_job_state(job: Job, to_state: str, **values: Any) -> None:
    """Move a loaded job to `to_state` (IllegalTransition if the table forbids it) and set other columns."""
    _, dst = check_job_edge(job.state, to_state)
    job.state = dst
    for name, value in values.items():
        setattr(job, name, value)
