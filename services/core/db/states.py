"""Where a task or a job changes state: the allowed transitions and the two functions that make them.

Every task state change goes through `transition()`, which moves the tasks with one conditional UPDATE and
adjusts the job's progress counters (`job_counter`) in the same transaction (on Postgres in the same statement); every job state change goes
through `set_job_state()` (or, for the planner's conditional claim, `check_job_edge()` first). A change not in
the tables below raises IllegalTransition, so a new code path cannot invent an edge silently.
"""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import (
    Case,
    ColumnElement,
    Row,
    Select,
    Table,
    Update,
    case,
    exists,
    func,
    literal,
    or_,
    select,
    text,
    update,
)
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session, aliased
from sqlalchemy.sql.selectable import TextualSelect

from services.core.db.bulk import connection_of
from services.core.db.counters import COUNTER_SHARDS, add_counts
from services.core.db.models import Job, JobState, Task, TaskState, WorkerBlock
from services.core.domain.cues import CATALOG, closure

__all__ = [
    "JOB_EDGES", "TASK_EDGES", "IllegalTransition", "JobState", "TaskState", "check_job_edge", "check_task_edge",
    "claim_task", "claim_view_tasks", "finish_task", "finish_tasks", "set_job_state", "task_state", "transition",
    "transition_rows",
]

# from -> the states a task may go to, and who takes that edge
TASK_EDGES: Mapping[TaskState, frozenset[TaskState]] = {
    # dispatch sends it; dispatch fails it (its pass failed for good); cancel_job; a view batch claims it with
    # its view's passes (the worker that rendered the view derives it from the pass set in memory: no message)
    TaskState.PENDING: frozenset({TaskState.QUEUED, TaskState.FAILED, TaskState.CANCELLED, TaskState.RUNNING}),
    # dispatch/reaper/worker give it back (paused job, lost message, resume); the worker claims it; cancel_job
    TaskState.QUEUED: frozenset({TaskState.PENDING, TaskState.RUNNING, TaskState.CANCELLED}),
    # reaper/requeue (lease ran out, interrupted), or a view batch hands back a task whose in-batch input failed;
    # the worker finishes or fails it; reaper of a cancelled job
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
    rows = transition_rows(session, job_id=job_id, from_state=from_state, to_state=to_state, task_ids=task_ids,
                           where=where, returning=(), **values)
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


# The counter half of a Postgres move, as SQL text: SQLAlchemy cannot cache the compiled form of an
# INSERT ... ON CONFLICT DO UPDATE construct (its cache key is None), and compiling the whole statement anew
# for every claim and result cost more CPU than Postgres spent running it. States are inlined: they come from
# the TaskState enum, never from input.
_COUNT_SQL = (
    "INSERT INTO job_counter (job_id, cue, state, shard, n) "
    "SELECT m.job_id, m.cue, d.state, mod(pg_backend_pid(), {shards}), d.sign * count(*) "
    "FROM moved AS m CROSS JOIN (VALUES ('{src}', -1), ('{dst}', 1)) AS d (state, sign) "
    "GROUP BY m.job_id, m.cue, d.state, d.sign ORDER BY m.job_id, m.cue, d.state "  # a fixed order, as add_counts:
    "ON CONFLICT (job_id, cue, state, shard) DO UPDATE SET n = job_counter.n + excluded.n"  # rows locked alike
)


@functools.cache
def _count_moved(src: str, dst: str) -> TextualSelect:
    return text(_COUNT_SQL.format(shards=COUNTER_SHARDS, src=TaskState(src).value, dst=TaskState(dst).value)).columns()


def _counted(move: Update, src: str, dst: str) -> Select[Any]:
    """WITH moved AS (UPDATE task ... RETURNING ...), counted AS (INSERT INTO job_counter ... ON CONFLICT add)
    SELECT * FROM moved: the move and its counter deltas in one statement (Postgres)."""
    moved = move.cte("moved")
    counted = _count_moved(src, dst).cte("counted")
    return select(moved).add_cte(moved, counted)  # in this order: counted reads moved


def set_job_state(job: Job, to_state: str, **values: object) -> None:
    """Move a loaded job to `to_state` (IllegalTransition if the table forbids it) and set other columns."""
    _, dst = check_job_edge(job.state, to_state)
    job.state = dst
    for name, value in values.items():
        setattr(job, name, value)


# ------------------------------------------------------------------------------------------ a worker's two moves
# A worker claims and finishes tasks one at a time, hundreds of them a second across a fleet: on Postgres these
# two moves are fixed SQL sent as is (no statement built, keyed and compiled per call, which cost a worker
# ~2 ms of CPU per move), each one statement with its counter deltas. Elsewhere they go through transition_rows.

_CLAIM_SQL = (
    "WITH moved AS (UPDATE task SET state = 'running', worker_id = %(worker)s, attempts = task.attempts + 1, "
    "started_at = %(now)s, finished_at = NULL, lease_until = %(lease)s "
    "WHERE task.id = %(task_id)s AND task.state = 'queued' "
    "AND EXISTS (SELECT 1 FROM job WHERE job.id = task.job_id AND job.state = 'running') "
    "AND NOT EXISTS (SELECT 1 FROM worker_block AS b WHERE b.worker_id = %(worker)s AND b.job_id = task.job_id "
    "AND (b.until IS NULL OR b.until > %(now)s)) "
    "RETURNING task.id, task.cue, task.job_id, task.space_id, task.point_idx, task.view_idx, task.attempts), "
    "counted AS ({count}) SELECT * FROM moved"
)
_FINISH_SQL = (
    "WITH moved AS (UPDATE task SET state = 'done', output_key = %(key)s, size = %(size)s, sha256 = %(sha256)s, "
    "duration_s = %(duration_s)s, finished_at = %(now)s, lease_until = NULL, error = NULL "
    "WHERE task.id = %(task_id)s AND task.state = 'running' AND task.worker_id = %(worker)s "
    "RETURNING task.id, task.cue, task.job_id), counted AS ({count}) SELECT * FROM moved"
)
# A view batch: the rest of one view's tasks in one claim, and the finished ones in one result (their values as
# arrays, so the text stays the same whatever the batch's size). The claim takes queued tasks and, after the
# view's render (%(pending)s), pending ones too, unless a task of the view failed (then the dispatcher's rule,
# "fail what an input failed for", decides). The candidates are locked first (skipping rows another transaction
# holds, e.g. a dispatch pass queueing them), so the counter deltas subtract from each row's own old state.
_CLAIM_VIEW_SQL = (
    "WITH cand AS (SELECT t.id, t.state AS old_state FROM task AS t "
    "WHERE t.job_id = %(job_id)s AND t.space_id = %(space_id)s AND t.point_idx = %(point)s "
    "AND t.view_idx = %(view)s AND t.cue <> 'passes' AND t.id <> %(task_id)s "
    "AND (t.state = 'queued' OR (%(pending)s AND t.state = 'pending' AND NOT EXISTS (SELECT 1 FROM task AS f "
    "WHERE f.job_id = t.job_id AND f.space_id = t.space_id AND f.point_idx = t.point_idx "
    "AND f.view_idx = t.view_idx AND f.state = 'failed'))) "
    "AND EXISTS (SELECT 1 FROM job WHERE job.id = t.job_id AND job.state = 'running') "
    "AND NOT EXISTS (SELECT 1 FROM worker_block AS b WHERE b.worker_id = %(worker)s AND b.job_id = t.job_id "
    "AND (b.until IS NULL OR b.until > %(now)s)) ORDER BY t.id FOR UPDATE OF t SKIP LOCKED), "
    "moved AS (UPDATE task SET state = 'running', worker_id = %(worker)s, attempts = task.attempts + 1, "
    "started_at = %(now)s, finished_at = NULL, lease_until = %(lease)s FROM cand "
    "WHERE task.id = cand.id RETURNING task.id, task.cue, task.job_id, task.attempts, cand.old_state), "
    "counted AS (INSERT INTO job_counter (job_id, cue, state, shard, n) "
    "SELECT m.job_id, m.cue, d.state, mod(pg_backend_pid(), {shards}), sum(d.sign) FROM moved AS m "
    "CROSS JOIN LATERAL (VALUES (m.old_state, -1), ('{dst}', 1)) AS d (state, sign) "
    "GROUP BY m.job_id, m.cue, d.state ORDER BY m.job_id, m.cue, d.state "
    "ON CONFLICT (job_id, cue, state, shard) DO UPDATE SET n = job_counter.n + excluded.n) "
    "SELECT moved.*, (SELECT count(*) FROM task AS v WHERE v.job_id = %(job_id)s AND v.space_id = %(space_id)s "
    "AND v.point_idx = %(point)s AND v.view_idx = %(view)s AND v.state <> 'done' AND v.cue NOT IN ({no_passes}) "
    "AND v.id NOT IN (SELECT id FROM moved)) AS reading_elsewhere FROM moved"
)
# Cues whose task never reads the view's pass set (the plan's), and `passes` itself: the claim's last column counts
# the view's other unfinished tasks, which may still need the stored pass set.
NO_PASSES: tuple[str, ...] = tuple(c for c in CATALOG if "passes" not in closure([c]) or c == "passes")
_FINISH_MANY_SQL = (
    "WITH moved AS (UPDATE task SET state = 'done', output_key = v.key, size = v.size, sha256 = v.sha256, "
    "duration_s = v.duration_s, finished_at = %(now)s, lease_until = NULL, error = NULL "
    "FROM unnest(%(ids)s::bigint[], %(keys)s::text[], %(sizes)s::bigint[], %(sha256s)s::text[], "
    "%(durations)s::float8[]) AS v (id, key, size, sha256, duration_s) "
    "WHERE task.id = v.id AND task.state = 'running' AND task.worker_id = %(worker)s "
    "RETURNING task.id, task.cue, task.job_id), counted AS ({count}) SELECT * FROM moved"
)
TASK_STATE_SQL = "SELECT state FROM task WHERE id = %(task_id)s"


def _worker_sql(template: str, src: TaskState, dst: TaskState) -> str:
    check_task_edge(src, dst)
    return template.format(count=_COUNT_SQL.format(shards=COUNTER_SHARDS, src=src.value, dst=dst.value))


CLAIM_SQL = _worker_sql(_CLAIM_SQL, TaskState.QUEUED, TaskState.RUNNING)
FINISH_SQL = _worker_sql(_FINISH_SQL, TaskState.RUNNING, TaskState.DONE)
CLAIM_VIEW_SQL = _CLAIM_VIEW_SQL.format(shards=COUNTER_SHARDS, dst=TaskState.RUNNING.value,
                                        no_passes=", ".join(f"'{c}'" for c in NO_PASSES))
check_task_edge(TaskState.QUEUED, TaskState.RUNNING)
check_task_edge(TaskState.PENDING, TaskState.RUNNING)
FINISH_MANY_SQL = _worker_sql(_FINISH_MANY_SQL, TaskState.RUNNING, TaskState.DONE)


def _autocommit(session: Session) -> Connection | None:
    """The session's connection outside a transaction on Postgres (one fixed statement, one round trip); None
    elsewhere."""
    if session.get_bind().dialect.name != "postgresql":
        return None
    return session.connection(execution_options={"isolation_level": "AUTOCOMMIT"})


def claim_task(session: Session, *, task_id: int, worker_id: str, now: datetime, lease_until: datetime) -> Row[Any] | None:
    """queued -> running for `worker_id` while the task's job runs and the worker is not kept off the job (a
    current WorkerBlock); returns the row (id, cue, job_id, space_id, point_idx, view_idx, attempts, attempts
    counting this one), or None when nothing was claimed. Postgres: one statement outside a transaction."""
    if session.get_bind().dialect.name == "postgresql":
        conn = session.connection(execution_options={"isolation_level": "AUTOCOMMIT"})
        return conn.exec_driver_sql(CLAIM_SQL, {"task_id": task_id, "worker": worker_id, "now": now,
                                                "lease": lease_until}).first()
    job_running = exists().where(Job.id == Task.job_id, Job.state == JobState.RUNNING)
    blocked = exists().where(WorkerBlock.worker_id == worker_id, WorkerBlock.job_id == Task.job_id,
                             or_(WorkerBlock.until.is_(None), WorkerBlock.until > now))
    rows = transition_rows(
        session, job_id=None, task_ids=[task_id], from_state=TaskState.QUEUED, to_state=TaskState.RUNNING,
        where=[job_running, ~blocked], returning=[Task.space_id, Task.point_idx, Task.view_idx, Task.attempts],
        worker_id=worker_id, attempts=Task.attempts + 1, started_at=now, finished_at=None, lease_until=lease_until,
    )
    session.commit()
    return rows[0] if rows else None


def finish_task(
    session: Session, *, task_id: int, job_id: int, worker_id: str, key: str, size: int, sha256: str | None,
    duration_s: float, now: datetime,
) -> bool:
    """running -> done for a task `worker_id` still holds, with its output; False when it no longer held it
    (reaped or cancelled meanwhile). Postgres: one statement outside a transaction."""
    values = {"key": key, "size": size, "sha256": sha256, "duration_s": duration_s, "now": now}
    if session.get_bind().dialect.name == "postgresql":
        conn = session.connection(execution_options={"isolation_level": "AUTOCOMMIT"})
        return conn.exec_driver_sql(FINISH_SQL, {"task_id": task_id, "worker": worker_id, **values}).first() is not None
    moved = transition(
        session, job_id=job_id, task_ids=[task_id], from_state=TaskState.RUNNING, to_state=TaskState.DONE,
        where=[Task.worker_id == worker_id], output_key=key, size=size, sha256=sha256, duration_s=duration_s,
        finished_at=now, lease_until=None, error=None,
    )
    session.commit()
    return bool(moved)


def claim_view_tasks(
    session: Session, *, task_id: int, job_id: int, space_id: int, point: int, view: int, worker_id: str,
    now: datetime, lease_until: datetime, with_pending: bool = False,
) -> list[Row[Any]] | list[tuple[Any, ...]]:
    """queued (and with `with_pending`, pending) -> running for `worker_id`, in one statement, of the view's other
    tasks (same job, space, point and view; not `task_id`, not its `passes` task) while the job runs and the worker
    is not kept off it; pending ones only while no task of the view failed. Returns the rows (id, cue, job_id,
    attempts counting this one, old state, reading_elsewhere: how many other tasks of the view that read its pass
    set are not done and not claimed here). Postgres: one fixed statement outside a transaction."""
    conn = _autocommit(session)
    if conn is not None:
        return list(conn.exec_driver_sql(CLAIM_VIEW_SQL, {
            "task_id": task_id, "job_id": job_id, "space_id": space_id, "point": point, "view": view,
            "worker": worker_id, "now": now, "lease": lease_until, "pending": with_pending}))
    job_running = exists().where(Job.id == Task.job_id, Job.state == JobState.RUNNING)
    blocked = exists().where(WorkerBlock.worker_id == worker_id, WorkerBlock.job_id == Task.job_id,
                             or_(WorkerBlock.until.is_(None), WorkerBlock.until > now))
    same_view = [Task.job_id == job_id, Task.space_id == space_id, Task.point_idx == point, Task.view_idx == view]
    rows: list[Row[Any]] = []
    for src in (TaskState.QUEUED, TaskState.PENDING) if with_pending else (TaskState.QUEUED,):
        where = [*same_view, Task.cue != "passes", Task.id != task_id, job_running, ~blocked]
        if src == TaskState.PENDING:
            f = aliased(Task)
            where.append(~exists().where(f.job_id == job_id, f.space_id == space_id, f.point_idx == point,
                                         f.view_idx == view, f.state == TaskState.FAILED))
        rows.extend(transition_rows(
            session, job_id=job_id, from_state=src, to_state=TaskState.RUNNING, where=where,
            returning=[Task.attempts, literal(src.value)], worker_id=worker_id, attempts=Task.attempts + 1,
            started_at=now, finished_at=None, lease_until=lease_until,
        ))
    moved = [int(r[0]) for r in rows]
    elsewhere = session.scalar(select(func.count()).select_from(Task).where(
        *same_view, Task.state != TaskState.DONE, Task.cue.not_in(NO_PASSES), Task.id.not_in(moved)))
    session.commit()
    return [(*r, int(elsewhere or 0)) for r in rows]


def finish_tasks(
    session: Session, *, job_id: int, worker_id: str, results: Sequence[tuple[int, str, int, str | None, float]],
    now: datetime,
) -> set[int]:
    """running -> done, in one statement, of the tasks `worker_id` still holds, each with its own output
    (task id, key, size, sha256, seconds); returns the ids moved. Postgres: one fixed statement over arrays,
    outside a transaction."""
    ids, keys, sizes, sha256s, durations = (list(col) for col in zip(*results, strict=True))
    conn = _autocommit(session)
    if conn is not None:
        rows = conn.exec_driver_sql(FINISH_MANY_SQL, {
            "ids": ids, "keys": keys, "sizes": sizes, "sha256s": sha256s, "durations": durations,
            "worker": worker_id, "now": now})
        return {int(r[0]) for r in rows}

    def per_task(values: Sequence[str | int | float | None]) -> Case[Any]:
        return case(dict(zip(ids, values, strict=True)), value=Task.id)

    moved = transition(
        session, job_id=job_id, task_ids=ids, from_state=TaskState.RUNNING, to_state=TaskState.DONE,
        where=[Task.worker_id == worker_id], output_key=per_task(keys), size=per_task(sizes),
        sha256=per_task(sha256s), duration_s=per_task(durations), finished_at=now, lease_until=None, error=None,
    )
    session.commit()
    return {tid for tid, _ in moved}


def task_state(session: Session, task_id: int) -> str | None:
    """The task's state (None: no such task), read without a lock; Postgres: outside a transaction."""
    conn = _autocommit(session)
    if conn is not None:
        return conn.exec_driver_sql(TASK_STATE_SQL, {"task_id": task_id}).scalar_one_or_none()
    return session.execute(select(Task.state).where(Task.id == task_id)).scalar_one_or_none()
