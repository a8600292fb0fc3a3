"""Where a task or a job changes state: the allowed transitions and the two functions that make them.

Every task state change goes through `transition()`, which moves the tasks with one conditional UPDATE and
adjusts the job's progress counters (`job_counter`) in the same transaction (on Postgres in the same
statement), except a worker's own moves (claim and result: services.core.db.worker_moves), fixed SQL text
built here once for both engines (`task_update_sql`, `counted_sql`, `count_moved_rows`) over edges checked
here. Every job state change goes through `set_job_state()` (or, for the planner's conditional claim,
`check_job_edge()` first). A change not in the tables below raises IllegalTransition, so a new code path
cannot invent an edge silently.
"""

from __future__ import annotations

import functools
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from sqlalchemy import ColumnElement, Row, Select, Table, Update, select, text, update
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session
from sqlalchemy.sql.selectable import TextualSelect

from services.core.db.bulk import connection_of
from services.core.db.counters import COUNTER_SHARDS, add_counts
from services.core.db.models import Job, JobState, Task, TaskState

__all__ = [
    "JOB_EDGES", "TASK_EDGES", "IllegalTransition", "JobState", "TaskState", "check_job_edge",
    "check_task_edge", "count_moved_rows", "count_moved_sql", "counted_sql", "set_job_state",
    "task_update_sql", "transition", "transition_rows",
]

# from -> the states a task may go to, and who takes that edge
TASK_EDGES: Mapping[TaskState, frozenset[TaskState]] = {
    # dispatch sends it; dispatch fails it (its pass failed for good); cancel_job; a view batch claims it with
    # its view's passes (the worker that rendered the view derives it from the pass set in memory: no message)
    TaskState.PENDING: frozenset(
        {TaskState.QUEUED, TaskState.FAILED, TaskState.CANCELLED, TaskState.RUNNING}
    ),
    # dispatch/reaper/worker give it back (paused job, lost message, resume); the worker claims it; cancel_job
    TaskState.QUEUED: frozenset({TaskState.PENDING, TaskState.RUNNING, TaskState.CANCELLED}),
    # reaper/requeue (lease ran out, interrupted), or a view batch hands back a task whose in-batch input
    # failed; the worker finishes or fails it; reaper of a cancelled job
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
    job_id: int | None,
    from_state: str,
    to_state: str,
    task_ids: Iterable[int] | None = None,
    where: Iterable[ColumnElement[bool]] = (),
    **values: object,
) -> list[tuple[int, str]]:
    """Move the job's tasks in `from_state` to `to_state` and adjust the counters in the same transaction.

    `task_ids` limits the move to those tasks (None: every task of the job in `from_state`); `where` adds
    conditions (e.g. the worker still holds it); `values` are further columns to set (values or SQL
    expressions, e.g. attempts=Task.attempts + 1). Tasks not in `from_state` are left alone, which makes
    racing transitions safe: only the (id, cue) pairs returned were moved, and only those are counted.
    `job_id` None (a worker holding only a task id) moves the given tasks of whatever job they belong to.
    Task objects already loaded in a Session are not refreshed (reload with populate_existing=True).
    """
    rows = transition_rows(
        session, job_id=job_id, from_state=from_state, to_state=to_state, task_ids=task_ids, where=where,
        returning=(),
        **values,
    )
    return [(int(r[0]), str(r[1])) for r in rows]


def transition_rows(
    session: Session | Connection,
    *,
    job_id: int | None,
    from_state: str,
    to_state: str,
    task_ids: Iterable[int] | None = None,
    where: Iterable[ColumnElement[bool]] = (),
    returning: Sequence[Any] = (),  # ORM attributes or columns (SQLAlchemy's column-clause argument)
    **values: object,
) -> list[Row[Any]]:
    """`transition`, returning rows of (id, cue, job_id, *returning) of the moved tasks.

    On Postgres the move and its counter deltas are ONE statement (a data-modifying CTE): the counter rows are
    locked for that statement only, and a worker's claim or result costs one round trip.
    """
    if job_id is None and task_ids is None:
        raise ValueError("transition: give a job_id or the task_ids to move")
    src, dst = check_task_edge(from_state, to_state)
    conn = connection_of(session)
    t = Task.__table__
    assert isinstance(t, Table)
    conds = [t.c.state == src.value, *where]
    if job_id is not None:
        conds.append(t.c.job_id == job_id)
    stmt = update(t).values(state=dst.value, **values).returning(t.c.id, t.c.cue, t.c.job_id, *returning)
    chunks: list[list[int] | None] = [None]
    if task_ids is not None:
        ids = list(dict.fromkeys(int(i) for i in task_ids))
        chunks = [ids[k : k + IN_CHUNK] for k in range(0, len(ids), IN_CHUNK)]
    moved: list[Row[Any]] = []
    for chunk in chunks:
        part = stmt.where(*conds) if chunk is None else stmt.where(t.c.id.in_(chunk), *conds)
        if conn.dialect.name == "postgresql":
            moved.extend(conn.execute(_counted(part, src.value, dst.value)))
            continue
        got = list(conn.execute(part))
        moved.extend(got)
        count_moved_rows(conn, got, src.value, dst)
    return moved


# The counter half of a Postgres move, as SQL text: SQLAlchemy cannot cache the compiled form of an
# INSERT ... ON CONFLICT DO UPDATE construct (its cache key is None), and compiling the whole statement anew
# for every claim and result cost more CPU than Postgres spent running it. States are inlined: they come from
# the TaskState enum, never from input.
def count_moved_sql(src_sql: str, dst: TaskState) -> str:
    """INSERT INTO job_counter the deltas of the rows of the CTE `moved` (job_id, cue): -1 in the state
    `src_sql` (a quoted state, or SQL naming a moved row's old state), +1 in `dst`."""
    return (
        "INSERT INTO job_counter (job_id, cue, state, shard, n) "
        f"SELECT m.job_id, m.cue, d.state, mod(pg_backend_pid(), {COUNTER_SHARDS}), sum(d.sign) "
        f"FROM moved AS m CROSS JOIN LATERAL (VALUES ({src_sql}, -1), ('{dst.value}', 1)) AS d (state, sign) "
        # a fixed order, as add_counts: rows locked alike
        "GROUP BY m.job_id, m.cue, d.state ORDER BY m.job_id, m.cue, d.state "
        "ON CONFLICT (job_id, cue, state, shard) DO UPDATE SET n = job_counter.n + excluded.n"
    )


@functools.cache
def _count_moved(src: str, dst: str) -> TextualSelect:
    return text(count_moved_sql(f"'{TaskState(src).value}'", TaskState(dst))).columns()


def _counted(move: Update, src: str, dst: str) -> Select[Any]:
    """WITH moved AS (UPDATE task ... RETURNING ...), counted AS (INSERT INTO job_counter ... ON CONFLICT add)
    SELECT * FROM moved: the move and its counter deltas in one statement (Postgres)."""
    moved = move.cte("moved")
    counted = _count_moved(src, dst).cte("counted")
    return select(moved).add_cte(moved, counted)  # in this order: counted reads moved


def count_moved_rows(conn: Connection, rows: Sequence[Sequence[Any]], src: str | None,
                     dst: TaskState) -> None:
    """The counter deltas of moved rows (id, cue, job_id, ...) where no statement moved them (SQLite): -1 from
    `src` (None: the row's last column, its old state), +1 to `dst`."""
    per_job: dict[int, Counter[tuple[str, str]]] = {}
    for r in rows:
        cue, old = str(r[1]), src if src is not None else str(r[-1])
        deltas = per_job.setdefault(int(r[2]), Counter())
        deltas[(cue, old)] -= 1
        deltas[(cue, dst.value)] += 1
    for job_id, job_deltas in per_job.items():
        add_counts(conn, job_id, job_deltas)


def task_update_sql(srcs: Sequence[TaskState], dst: TaskState, sets: str, where: str, *, returning: str = "",
                    rows: str = "") -> str:
    """UPDATE task from `srcs` (each an edge to `dst`, IllegalTransition if not) to `dst`, setting `sets`
    where `where` (one source: in that state; several: `where` says which), optionally FROM `rows`,
    returning (id, cue, job_id, `returning`): the SQL text both engines run, parameters written `:name`."""
    for src in srcs:
        check_task_edge(src, dst)
    state = f" AND task.state = '{srcs[0].value}'" if len(srcs) == 1 else ""
    source = f" FROM {rows}" if rows else ""
    more = f", {returning}" if returning else ""
    return (f"UPDATE task SET state = '{dst.value}', {sets}{source} WHERE {where}{state} "
            f"RETURNING task.id, task.cue, task.job_id{more}")


def counted_sql(update: str, src_sql: str, dst: TaskState, *, before: str = "",
                select: str = "SELECT * FROM moved") -> str:
    """Postgres: `update` (task_update_sql) and its counter deltas as ONE statement (a data-modifying CTE
    after the CTEs `before`), parameters in psycopg's `%(name)s` style."""
    sql = f"WITH {before}moved AS ({update}), counted AS ({count_moved_sql(src_sql, dst)}) {select}"
    return re.sub(r"(?<![:\w]):(\w+)", r"%(\1)s", sql)  # :name, not a ::cast


def set_job_state(job: Job, to_state: str, **values: object) -> None:
    """Move a loaded job to `to_state` (IllegalTransition if the table forbids it) and set other columns."""
    _, dst = check_job_edge(job.state, to_state)
    job.state = dst
    for name, value in values.items():
        setattr(job, name, value)
