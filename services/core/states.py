"""Where a task or a job changes state: the allowed transitions and the two functions that make them.

Every task state change goes through `transition()`, which moves the tasks with one conditional UPDATE and
adjusts the job's progress counters (`job_counter`) in the same transaction (on Postgres in the same statement); every job state change goes
through `set_job_state()` (or, for the planner's conditional claim, `check_job_edge()` first). A change not in
the tables below raises IllegalTransition, so a new code path cannot invent an edge silently.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from sqlalchemy import ColumnElement, Table, func, literal, select, union_all, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from services.core.db import _IN_CHUNK, COUNTER_SHARDS, _connection, add_counts
from services.core.models import Job, JobCounter, JobState, Task, TaskState

__all__ = [
    "JOB_EDGES", "TASK_EDGES", "IllegalTransition", "JobState", "TaskState", "check_job_edge", "check_task_edge",
    "set_job_state", "transition", "transition_rows",
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
    job_id: int | None,
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
    `job_id` None (a worker holding only a task id) moves the given tasks of whatever job they belong to.
    Task objects already loaded in a Session are not refreshed (reload with populate_existing=True).
    """
    rows = transition_rows(session, job_id=job_id, from_state=from_state, to_state=to_state, task_ids=task_ids,
                           where=where, **values)
    return [(int(r[0]), str(r[1])) for r in rows]


def transition_rows(
    session: Session | Connection,
    *,
    job_id: int | None,
    from_state: str,
    to_state: str,
    task_ids: Iterable[int] | None = None,
    where: Iterable[ColumnElement[bool]] = (),
    returning: Sequence[Any] = (),
    **values: Any,
) -> list[Any]:
    """`transition`, returning rows of (id, cue, job_id, *returning) of the moved tasks.

    On Postgres the move and its counter deltas are ONE statement (a data-modifying CTE): the counter rows are
    locked for that statement only, and a worker's claim or result costs one round trip.
    """
    if job_id is None and task_ids is None:
        raise ValueError("transition: give a job_id or the task_ids to move")
    src, dst = check_task_edge(from_state, to_state)
    conn = _connection(session)
    t = Task.__table__
    assert isinstance(t, Table)
    conds = [t.c.state == src.value, *where]
    if job_id is not None:
        conds.append(t.c.job_id == job_id)
    stmt = update(t).values(state=dst.value, **values).returning(t.c.id, t.c.cue, t.c.job_id, *returning)
    chunks: list[list[int] | None] = [None]
    if task_ids is not None:
        ids = list(dict.fromkeys(int(i) for i in task_ids))
        chunks = [ids[k : k + _IN_CHUNK] for k in range(0, len(ids), _IN_CHUNK)]
    moved: list[Any] = []
    for chunk in chunks:
        part = stmt.where(*conds) if chunk is None else stmt.where(t.c.id.in_(chunk), *conds)
        if conn.dialect.name == "postgresql":
            moved.extend(conn.execute(_counted(part, src.value, dst.value)))
            continue
        got = list(conn.execute(part))
        moved.extend(got)
        per_job: dict[int, Counter[str]] = {}
        for r in got:
            per_job.setdefault(int(r[2]), Counter())[str(r[1])] += 1
        for jid, per_cue in per_job.items():
            deltas: dict[tuple[str, str], int] = {}
            for cue, k in per_cue.items():
                deltas[(cue, src.value)] = -k
                deltas[(cue, dst.value)] = k
            add_counts(conn, jid, deltas)
    return moved


def _counted(move: Any, src: str, dst: str) -> Any:
    """WITH moved AS (UPDATE task ... RETURNING ...), counted AS (INSERT INTO job_counter ... ON CONFLICT add)
    SELECT * FROM moved: the move and its counter deltas in one statement (Postgres)."""
    moved = move.cte("moved")
    per_cue = (
        select(moved.c.job_id, moved.c.cue, func.count().label("k")).group_by(moved.c.job_id, moved.c.cue).cte("per_cue")
    )
    shard = func.mod(func.pg_backend_pid(), COUNTER_SHARDS)
    deltas = union_all(
        select(per_cue.c.job_id, per_cue.c.cue, literal(src).label("state"), shard.label("shard"),
               (-per_cue.c.k).label("n")),
        select(per_cue.c.job_id, per_cue.c.cue, literal(dst).label("state"), shard.label("shard"),
               per_cue.c.k.label("n")),
    ).subquery()
    counters = JobCounter.__table__
    assert isinstance(counters, Table)
    ins = pg_insert(counters).from_select(
        ["job_id", "cue", "state", "shard", "n"],
        # a fixed order, as add_counts: concurrent statements lock the rows of a shard alike
        select(deltas).order_by(deltas.c.job_id, deltas.c.cue, deltas.c.state),
    )
    ins = ins.on_conflict_do_update(
        index_elements=["job_id", "cue", "state", "shard"], set_={"n": counters.c.n + ins.excluded.n}
    )
    return select(moved).add_cte(ins.cte("counted"))


def set_job_state(job: Job, to_state: str, **values: Any) -> None:
    """Move a loaded job to `to_state` (IllegalTransition if the table forbids it) and set other columns."""
    _, dst = check_job_edge(job.state, to_state)
    job.state = dst.value
    for name, value in values.items():
        setattr(job, name, value)
