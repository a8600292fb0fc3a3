"""A worker's own task moves as fixed SQL: claim a task, claim the rest of its view, record results, read a state.

A worker claims and finishes tasks one at a time, hundreds of them a second across a fleet, and an embedded run's
single worker does so for every view it renders: so these moves are SQL text sent as is, never a statement built,
keyed and compiled per call (that cost a worker ~2 ms of CPU a move on Postgres, ~5 ms a view on SQLite).
- Postgres: each move is ONE statement with its counter deltas (a data-modifying CTE), outside a transaction.
- SQLite: no data-modifying CTEs, so a move is its UPDATE ... RETURNING, then the counter upserts
  (counters.add_counts), in one transaction. SQLite has one writer at a time: the first UPDATE holds the write lock
  to the commit.
Each takes only task edges of states.TASK_EDGES (checked at import) and keeps the counters as `transition` does.
"""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import Any

from sqlalchemy.engine import Connection, Dialect
from sqlalchemy.orm import Session

from services.core.db.bulk import connection_of
from services.core.db.counters import COUNTER_SHARDS, add_counts
from services.core.db.models import Task
from services.core.db.states import COUNT_MOVED_SQL, TaskState, check_task_edge
from services.core.domain.cues import CATALOG, closure

__all__ = ["NO_PASSES", "claim_task", "claim_view_tasks", "finish_task", "finish_tasks", "task_state"]

# Cues whose task never reads the view's pass set (the plan's), and `passes` itself: a view claim counts the view's
# other unfinished tasks, which may still need the stored pass set.
NO_PASSES: tuple[str, ...] = tuple(c for c in CATALOG if "passes" not in closure([c]) or c == "passes")
_NO_PASSES_SQL = ", ".join(f"'{c}'" for c in NO_PASSES)

for _edge in ((TaskState.QUEUED, TaskState.RUNNING), (TaskState.PENDING, TaskState.RUNNING),
              (TaskState.RUNNING, TaskState.DONE)):
    check_task_edge(*_edge)

# ------------------------------------------------------------------------------------------------------- Postgres
_PG_CLAIM = (
    "WITH moved AS (UPDATE task SET state = 'running', worker_id = %(worker)s, attempts = task.attempts + 1, "
    "started_at = %(now)s, finished_at = NULL, lease_until = %(lease)s "
    "WHERE task.id = %(task_id)s AND task.state = 'queued' "
    "AND EXISTS (SELECT 1 FROM job WHERE job.id = task.job_id AND job.state = 'running') "
    "AND NOT EXISTS (SELECT 1 FROM worker_block AS b WHERE b.worker_id = %(worker)s AND b.job_id = task.job_id "
    "AND (b.until IS NULL OR b.until > %(now)s)) "
    "RETURNING task.id, task.cue, task.job_id, task.space_id, task.point_idx, task.view_idx, task.attempts), "
    "counted AS ({count}) SELECT * FROM moved"
)
# A view batch: the rest of one view's tasks in one claim, and the finished ones in one result (their values as
# arrays, so the text stays the same whatever the batch's size). The claim takes queued tasks and, after the
# view's render (%(pending)s), pending ones too, unless a task of the view failed (then the dispatcher's rule,
# "fail what an input failed for", decides). The candidates are locked first (skipping rows another transaction
# holds, e.g. a dispatch pass queueing them), so the counter deltas subtract from each row's own old state.
_PG_CLAIM_VIEW = (
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
    "CROSS JOIN LATERAL (VALUES (m.old_state, -1), ('running', 1)) AS d (state, sign) "
    "GROUP BY m.job_id, m.cue, d.state ORDER BY m.job_id, m.cue, d.state "
    "ON CONFLICT (job_id, cue, state, shard) DO UPDATE SET n = job_counter.n + excluded.n) "
    "SELECT moved.*, (SELECT count(*) FROM task AS v WHERE v.job_id = %(job_id)s AND v.space_id = %(space_id)s "
    "AND v.point_idx = %(point)s AND v.view_idx = %(view)s AND v.state <> 'done' AND v.cue NOT IN ({no_passes}) "
    "AND v.id <> %(task_id)s AND v.id NOT IN (SELECT id FROM moved)) AS reading_elsewhere FROM moved"
)
_PG_FINISH_MANY = (
    "WITH moved AS (UPDATE task SET state = 'done', output_key = v.key, size = v.size, sha256 = v.sha256, "
    "duration_s = v.duration_s, finished_at = %(now)s, lease_until = NULL, error = NULL "
    "FROM unnest(%(ids)s::bigint[], %(keys)s::text[], %(sizes)s::bigint[], %(sha256s)s::text[], "
    "%(durations)s::float8[]) AS v (id, key, size, sha256, duration_s) "
    "WHERE task.id = v.id AND task.state = 'running' AND task.worker_id = %(worker)s "
    "RETURNING task.id, task.cue, task.job_id), counted AS ({count}) SELECT * FROM moved"
)
TASK_STATE_SQL = "SELECT state FROM task WHERE id = %(task_id)s"


def _with_counts(template: str, src: TaskState, dst: TaskState) -> str:
    return template.format(count=COUNT_MOVED_SQL.format(shards=COUNTER_SHARDS, src=src.value, dst=dst.value))


CLAIM_SQL = _with_counts(_PG_CLAIM, TaskState.QUEUED, TaskState.RUNNING)
CLAIM_VIEW_SQL = _PG_CLAIM_VIEW.format(shards=COUNTER_SHARDS, no_passes=_NO_PASSES_SQL)
FINISH_MANY_SQL = _with_counts(_PG_FINISH_MANY, TaskState.RUNNING, TaskState.DONE)

# --------------------------------------------------------------------------------------------------------- SQLite
# The same conditions; each UPDATE returns the moved rows, whose counters add_counts then moves.
_MAY_CLAIM = (  # the job runs and the worker is not kept off it
    "EXISTS (SELECT 1 FROM job WHERE job.id = task.job_id AND job.state = 'running') "
    "AND NOT EXISTS (SELECT 1 FROM worker_block AS b WHERE b.worker_id = :worker AND b.job_id = task.job_id "
    "AND (b.until IS NULL OR b.until > :now))"
)
_CLAIMED = ("UPDATE task SET state = 'running', worker_id = :worker, attempts = attempts + 1, started_at = :now, "
            "finished_at = NULL, lease_until = :lease ")
SQLITE_CLAIM_SQL = (f"{_CLAIMED}WHERE id = :task_id AND state = 'queued' AND {_MAY_CLAIM} "
                    "RETURNING id, cue, job_id, space_id, point_idx, view_idx, attempts")
_SAME_VIEW = "job_id = :job_id AND space_id = :space_id AND point_idx = :point AND view_idx = :view"
SQLITE_CLAIM_VIEW_SQL = (  # :src is 'queued' or 'pending' (a pending task only while no task of its view failed)
    f"{_CLAIMED}WHERE {_SAME_VIEW} AND cue <> 'passes' AND id <> :task_id AND state = :src "
    "AND (:src = 'queued' OR NOT EXISTS (SELECT 1 FROM task AS f WHERE f.job_id = task.job_id "
    "AND f.space_id = task.space_id AND f.point_idx = task.point_idx AND f.view_idx = task.view_idx "
    f"AND f.state = 'failed')) AND {_MAY_CLAIM} RETURNING id, cue, job_id, attempts"
)
SQLITE_VIEW_READERS_SQL = f"SELECT id FROM task WHERE {_SAME_VIEW} AND state <> 'done' AND cue NOT IN ({_NO_PASSES_SQL})"
SQLITE_FINISH_SQL = (
    "UPDATE task SET state = 'done', output_key = :key, size = :size, sha256 = :sha256, duration_s = :duration_s, "
    "finished_at = :now, lease_until = NULL, error = NULL WHERE id = :task_id AND state = 'running' "
    "AND worker_id = :worker RETURNING id, cue, job_id"
)
SQLITE_TASK_STATE_SQL = "SELECT state FROM task WHERE id = :task_id"


def _bound_time(conn: Connection, t: datetime) -> Any:
    """`t` as the ORM writes a UTCDateTime column on this connection (SQLite: naive UTC text), so that fixed SQL
    writes and compares the same values: the column type's own bind processor."""
    return _time_binder(conn.dialect)(t)


@functools.cache
def _time_binder(dialect: Dialect) -> Callable[[datetime], Any]:
    process = Task.__table__.c.started_at.type.bind_processor(dialect)
    return process if process is not None else (lambda t: t)


def _autocommit(session: Session) -> Connection | None:
    """The session's connection outside a transaction on Postgres (one fixed statement, one round trip); None
    elsewhere."""
    if session.get_bind().dialect.name != "postgresql":
        return None
    return session.connection(execution_options={"isolation_level": "AUTOCOMMIT"})


def _count_sqlite(conn: Connection, rows: Sequence[Sequence[Any]], src: str | None, dst: str) -> None:
    """Counter deltas of moved rows (id, cue, job_id, ...): -1 from `src` (None: the row's 5th column, its old
    state), +1 to `dst`."""
    per_job: dict[int, Counter[tuple[str, str]]] = {}
    for r in rows:
        cue, old = str(r[1]), src if src is not None else str(r[4])
        deltas = per_job.setdefault(int(r[2]), Counter())
        deltas[(cue, old)] -= 1
        deltas[(cue, dst)] += 1
    for job_id, deltas in per_job.items():
        add_counts(conn, job_id, deltas)


def claim_task(session: Session, *, task_id: int, worker_id: str, now: datetime, lease_until: datetime) -> Any:
    """queued -> running for `worker_id` while the task's job runs and the worker is not kept off the job (a
    current WorkerBlock); returns the row (id, cue, job_id, space_id, point_idx, view_idx, attempts, attempts
    counting this one), or None when nothing was claimed."""
    conn = _autocommit(session)
    if conn is not None:
        return conn.exec_driver_sql(CLAIM_SQL, {"task_id": task_id, "worker": worker_id, "now": now,
                                                "lease": lease_until}).first()
    conn = connection_of(session)
    rows = list(conn.exec_driver_sql(SQLITE_CLAIM_SQL, {
        "task_id": task_id, "worker": worker_id, "now": _bound_time(conn, now), "lease": _bound_time(conn, lease_until)}))
    _count_sqlite(conn, rows, TaskState.QUEUED.value, TaskState.RUNNING.value)
    session.commit()
    return rows[0] if rows else None


def finish_task(session: Session, *, task_id: int, worker_id: str, key: str, size: int, sha256: str | None,
                duration_s: float, now: datetime) -> bool:
    """running -> done for a task `worker_id` still holds, with its output; False when it no longer held it
    (reaped or cancelled meanwhile)."""
    return bool(finish_tasks(session, worker_id=worker_id, now=now, results=[(task_id, key, size, sha256, duration_s)]))


def claim_view_tasks(
    session: Session, *, task_id: int, job_id: int, space_id: int, point: int, view: int, worker_id: str,
    now: datetime, lease_until: datetime, with_pending: bool = False,
) -> list[Any]:
    """queued (and with `with_pending`, pending) -> running for `worker_id`, at once, of the view's other
    tasks (same job, space, point and view; not `task_id`, not its `passes` task) while the job runs and the worker
    is not kept off it; pending ones only while no task of the view failed. Returns the rows (id, cue, job_id,
    attempts counting this one, old state, reading_elsewhere: how many other tasks of the view that read its pass
    set are not done and not claimed here, `task_id` counting as claimed here). Postgres: one statement; SQLite: an
    UPDATE per source state, a read of the view's readers and the counters, in one transaction."""
    params: dict[str, Any] = {"task_id": task_id, "job_id": job_id, "space_id": space_id, "point": point,
                              "view": view, "worker": worker_id, "now": now, "lease": lease_until}
    conn = _autocommit(session)
    if conn is not None:
        return list(conn.exec_driver_sql(CLAIM_VIEW_SQL, {**params, "pending": with_pending}))
    conn = connection_of(session)
    params.update(now=_bound_time(conn, now), lease=_bound_time(conn, lease_until))
    rows: list[tuple[Any, ...]] = []
    for src in (TaskState.QUEUED, TaskState.PENDING) if with_pending else (TaskState.QUEUED,):
        # RETURNING gives the new state: the old one is the source state this UPDATE moved from
        rows += [(*r[:4], src.value) for r in conn.exec_driver_sql(SQLITE_CLAIM_VIEW_SQL, {**params, "src": src.value})]
    _count_sqlite(conn, rows, None, TaskState.RUNNING.value)
    moved = {int(r[0]) for r in rows}
    readers = {int(r[0]) for r in conn.exec_driver_sql(SQLITE_VIEW_READERS_SQL, params)}
    session.commit()
    return [(*r, len(readers - moved - {task_id})) for r in rows]


def finish_tasks(
    session: Session, *, worker_id: str, results: Sequence[tuple[int, str, int, str | None, float]], now: datetime,
) -> set[int]:
    """running -> done of the tasks `worker_id` still holds, each with its own output (task id, key, size, sha256,
    seconds); returns the ids moved. Postgres: one fixed statement over arrays, outside a transaction; SQLite: one
    UPDATE per task in one transaction."""
    conn = _autocommit(session)
    if conn is not None:
        ids, keys, sizes, sha256s, durations = (list(col) for col in zip(*results, strict=True))
        rows = conn.exec_driver_sql(FINISH_MANY_SQL, {
            "ids": ids, "keys": keys, "sizes": sizes, "sha256s": sha256s, "durations": durations,
            "worker": worker_id, "now": now})
        return {int(r[0]) for r in rows}
    conn = connection_of(session)
    finished = _bound_time(conn, now)
    moved: list[Any] = []
    for tid, key, size, sha256, duration in results:
        moved += conn.exec_driver_sql(SQLITE_FINISH_SQL, {
            "task_id": tid, "key": key, "size": size, "sha256": sha256, "duration_s": duration, "worker": worker_id,
            "now": finished}).all()
    _count_sqlite(conn, moved, TaskState.RUNNING.value, TaskState.DONE.value)
    session.commit()
    return {int(r[0]) for r in moved}


def task_state(session: Session, task_id: int) -> str | None:
    """The task's state (None: no such task), read without a lock; Postgres: outside a transaction."""
    conn = _autocommit(session)
    if conn is not None:
        return conn.exec_driver_sql(TASK_STATE_SQL, {"task_id": task_id}).scalar_one_or_none()
    return connection_of(session).exec_driver_sql(SQLITE_TASK_STATE_SQL, {"task_id": task_id}).scalar_one_or_none()
