"""A worker's own task moves as fixed SQL: claim a task, claim the rest of its view, record results, read a
state.

A worker claims and finishes tasks one at a time, hundreds of them a second across a fleet, and an embedded
run's single worker does so for every view it renders: so these moves are SQL text sent as is, never a
statement built, keyed and compiled per call (that cost a worker ~2 ms of CPU a move on Postgres, ~5 ms a view
on SQLite). Each move is written once and built for both engines by states.task_update_sql (which checks its
edges):
- Postgres: each move is ONE statement with its counter deltas (a data-modifying CTE), outside a transaction.
- SQLite: no data-modifying CTEs, so a move is its UPDATE ... RETURNING, then the counter upserts
  (states.count_moved_rows), in one transaction. SQLite has one writer at a time: the first UPDATE holds
  the write lock to the commit.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import Any

from sqlalchemy.engine import Connection, Dialect
from sqlalchemy.orm import Session

from services.core.db.bulk import connection_of
from services.core.db.models import Task
from services.core.db.states import TaskState, count_moved_rows, counted_sql, task_update_sql
from services.core.domain.cues import CATALOG, closure

__all__ = ["NO_PASSES", "claim_task", "claim_view_tasks", "finish_task", "finish_tasks", "task_state"]

QUEUED, PENDING, RUNNING, DONE = TaskState.QUEUED, TaskState.PENDING, TaskState.RUNNING, TaskState.DONE

# Cues whose task never reads the view's pass set (the plan's), and `passes` itself: a view claim counts the
# view's other unfinished tasks, which may still need the stored pass set.
NO_PASSES: tuple[str, ...] = tuple(c for c in CATALOG if "passes" not in closure([c]) or c == "passes")


def _may_claim(t: str) -> str:
    """The task `t`'s job runs and the worker is not kept off it."""
    return (f"EXISTS (SELECT 1 FROM job WHERE job.id = {t}.job_id AND job.state = 'running') "
            "AND NOT EXISTS (SELECT 1 FROM worker_block AS b WHERE b.worker_id = :worker "
            f"AND b.job_id = {t}.job_id AND (b.until IS NULL OR b.until > :now))")


def _same_view(t: str) -> str:
    return (f"{t}.job_id = :job_id AND {t}.space_id = :space_id AND {t}.point_idx = :point "
            f"AND {t}.view_idx = :view")


_CLAIMED = ("worker_id = :worker, attempts = task.attempts + 1, started_at = :now, finished_at = NULL, "
            "lease_until = :lease")
_CLAIM = task_update_sql([QUEUED], RUNNING, _CLAIMED, f"task.id = :task_id AND {_may_claim('task')}",
                         returning="task.space_id, task.point_idx, task.view_idx, task.attempts")
CLAIM_SQL = counted_sql(_CLAIM, f"'{QUEUED.value}'", RUNNING)
SQLITE_CLAIM_SQL = _CLAIM

# A view batch: the rest of one view's tasks in one claim, and the finished ones in one result. The claim
# takes queued tasks and, after the view's render (pending), pending ones too, unless a task of the view
# failed (then the dispatcher's rule, "fail what an input failed for", decides).
_VIEW_CANDIDATES = f"{_same_view('t')} AND t.cue <> 'passes' AND t.id <> :task_id AND {_may_claim('t')}"
_NONE_FAILED = ("NOT EXISTS (SELECT 1 FROM task AS f WHERE f.job_id = t.job_id AND f.space_id = t.space_id "
                "AND f.point_idx = t.point_idx AND f.view_idx = t.view_idx AND f.state = 'failed')")
# the view's other unfinished tasks: those the claim leaves (not moved) run or wait elsewhere
_UNFINISHED = f"{_same_view('v')} AND v.state <> 'done' AND v.id <> :task_id"
# Postgres: the candidates are locked first (skipping rows another transaction holds, e.g. a dispatch pass
# queueing them), so the counter deltas subtract from each row's own old state.
CLAIM_VIEW_SQL = counted_sql(
    task_update_sql([QUEUED, PENDING], RUNNING, _CLAIMED, "task.id = cand.id",
                    returning="task.attempts, cand.old_state", rows="cand"),
    "m.old_state", RUNNING,
    before=(f"cand AS (SELECT t.id, t.state AS old_state FROM task AS t WHERE {_VIEW_CANDIDATES} AND "
            f"(t.state = 'queued' OR (:pending AND t.state = 'pending' AND {_NONE_FAILED})) "
            "ORDER BY t.id FOR UPDATE OF t SKIP LOCKED), "),
    select=(f"SELECT moved.*, ARRAY(SELECT v.cue FROM task AS v WHERE {_UNFINISHED} "
            "AND v.id NOT IN (SELECT id FROM moved) ORDER BY v.cue) AS elsewhere FROM moved"))
# SQLite: one UPDATE per source state (RETURNING names only the updated table, not its old state)
SQLITE_CLAIM_VIEW_SQL = {
    src: task_update_sql([src], RUNNING, _CLAIMED,
                         f"task.id IN (SELECT t.id FROM task AS t WHERE {_VIEW_CANDIDATES}"
                         + (f" AND {_NONE_FAILED})" if src == PENDING else ")"), returning="task.attempts")
    for src in (QUEUED, PENDING)}
SQLITE_VIEW_UNFINISHED_SQL = f"SELECT v.id, v.cue FROM task AS v WHERE {_UNFINISHED} ORDER BY v.cue"

# The results as rows (the same text whatever the batch's size): arrays on Postgres, a JSON array on SQLite
_RESULTS = ("id", "key", "size", "sha256", "duration_s")
_RESULT_ROWS = {
    "postgresql": "unnest(:ids::bigint[], :keys::text[], :sizes::bigint[], :sha256s::text[], "
                  f":durations::float8[]) AS v ({', '.join(_RESULTS)})",
    "sqlite": "(SELECT " + ", ".join(f"j.value ->> {i} AS {c}" for i, c in enumerate(_RESULTS))
              + " FROM json_each(:results) AS j) AS v",
}


def _finish(dialect: str) -> str:
    return task_update_sql([RUNNING], DONE, "output_key = v.key, size = v.size, sha256 = v.sha256, "
                           "duration_s = v.duration_s, finished_at = :now, lease_until = NULL, error = NULL",
                           "task.id = v.id AND task.worker_id = :worker", rows=_RESULT_ROWS[dialect])


FINISH_MANY_SQL = counted_sql(_finish("postgresql"), f"'{RUNNING.value}'", DONE)
SQLITE_FINISH_SQL = _finish("sqlite")
TASK_STATE_SQL = "SELECT state FROM task WHERE id = %(task_id)s"
SQLITE_TASK_STATE_SQL = "SELECT state FROM task WHERE id = :task_id"


def _bound_time(conn: Connection, t: datetime) -> Any:
    """`t` as the ORM writes a UTCDateTime column on this connection (SQLite: naive UTC text), so that fixed
    SQL writes and compares the same values: the column type's own bind processor."""
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


def claim_task(
    session: Session, *, task_id: int, worker_id: str, now: datetime, lease_until: datetime
) -> Any:
    """queued -> running for `worker_id` while the task's job runs and the worker is not kept off the job (a
    current WorkerBlock); returns the row (id, cue, job_id, space_id, point_idx, view_idx, attempts, attempts
    counting this one), or None when nothing was claimed."""
    conn = _autocommit(session)
    if conn is not None:
        return conn.exec_driver_sql(CLAIM_SQL, {"task_id": task_id, "worker": worker_id, "now": now,
                                                "lease": lease_until}).first()
    conn = connection_of(session)
    rows = list(
        conn.exec_driver_sql(
            SQLITE_CLAIM_SQL,
            {
                "task_id": task_id, "worker": worker_id, "now": _bound_time(conn, now),
                "lease": _bound_time(conn, lease_until),
            },
        )
    )
    count_moved_rows(conn, rows, QUEUED.value, RUNNING)
    session.commit()
    return rows[0] if rows else None


def finish_task(session: Session, *, task_id: int, worker_id: str, key: str, size: int, sha256: str | None,
                duration_s: float, now: datetime) -> bool:
    """running -> done for a task `worker_id` still holds, with its output; False when it no longer held it
    (reaped or cancelled meanwhile)."""
    return bool(
        finish_tasks(
            session, worker_id=worker_id, now=now, results=[(task_id, key, size, sha256, duration_s)]
        )
    )


def claim_view_tasks(
    session: Session, *, task_id: int, job_id: int, space_id: int, point: int, view: int, worker_id: str,
    now: datetime, lease_until: datetime, with_pending: bool = False,
) -> list[Any]:
    """queued (and with `with_pending`, pending) -> running for `worker_id`, at once, of the view's other
    tasks (same job, space, point and view; not `task_id`, not its `passes` task) while the job runs and the
    worker is not kept off it; pending ones only while no task of the view failed. Returns the rows (id, cue,
    job_id, attempts counting this one, old state, reading_elsewhere, elsewhere): `elsewhere` the cues of
    the view's other tasks that are not done and not claimed here (running or waiting elsewhere, `task_id`
    counting as claimed here), `reading_elsewhere` how many of those read the pass set. Postgres: one
    statement; SQLite: an UPDATE per source state, a read of the view's unfinished tasks and the counters, in
    one transaction."""
    params: dict[str, Any] = {"task_id": task_id, "job_id": job_id, "space_id": space_id, "point": point,
                              "view": view, "worker": worker_id, "now": now, "lease": lease_until}
    conn = _autocommit(session)
    if conn is not None:
        return [(*r[:5], *_elsewhere(r[5])) for r in
                conn.exec_driver_sql(CLAIM_VIEW_SQL, {**params, "pending": with_pending})]
    conn = connection_of(session)
    params.update(now=_bound_time(conn, now), lease=_bound_time(conn, lease_until))
    rows: list[tuple[Any, ...]] = []
    for src in (QUEUED, PENDING) if with_pending else (QUEUED,):
        # RETURNING gives the new state: the old one is the source state this UPDATE moved from
        rows += [(*r[:4], src.value) for r in conn.exec_driver_sql(SQLITE_CLAIM_VIEW_SQL[src], params)]
    count_moved_rows(conn, rows, None, RUNNING)
    moved = {int(r[0]) for r in rows}
    unfinished = [str(c) for i, c in conn.exec_driver_sql(SQLITE_VIEW_UNFINISHED_SQL, params)
                  if i not in moved]
    session.commit()
    return [(*r, *_elsewhere(unfinished)) for r in rows]


def _elsewhere(cues: Sequence[str]) -> tuple[int, tuple[str, ...]]:
    """(how many of the view's tasks left elsewhere read the pass set, their cues)."""
    return sum(1 for c in cues if c not in NO_PASSES), tuple(cues)


def finish_tasks(
    session: Session,
    *,
    worker_id: str, results: Sequence[tuple[int, str, int, str | None, float]], now: datetime,
) -> set[int]:
    """running -> done of the tasks `worker_id` still holds, each with its own output (task id, key, size,
    sha256, seconds); returns the ids moved. One fixed statement over the results: Postgres (arrays) outside a
    transaction, SQLite (a JSON array) with its counters in one transaction."""
    conn = _autocommit(session)
    if conn is not None:
        ids, keys, sizes, sha256s, durations = (list(col) for col in zip(*results, strict=True))
        rows = conn.exec_driver_sql(FINISH_MANY_SQL, {
            "ids": ids, "keys": keys, "sizes": sizes, "sha256s": sha256s, "durations": durations,
            "worker": worker_id, "now": now})
        return {int(r[0]) for r in rows}
    conn = connection_of(session)
    results_json = json.dumps([[int(t), k, int(n), sha, float(d)] for t, k, n, sha, d in results])
    moved = conn.exec_driver_sql(SQLITE_FINISH_SQL, {"results": results_json, "worker": worker_id,
                                                     "now": _bound_time(conn, now)}).all()
    count_moved_rows(conn, moved, RUNNING.value, DONE)
    session.commit()
    return {int(r[0]) for r in moved}


def task_state(session: Session, task_id: int) -> str | None:
    """The task's state (None: no such task), read without a lock; Postgres: outside a transaction."""
    conn = _autocommit(session)
    if conn is not None:
        return conn.exec_driver_sql(TASK_STATE_SQL, {"task_id": task_id}).scalar_one_or_none()
    return (
        connection_of(session)
        .exec_driver_sql(SQLITE_TASK_STATE_SQL, {"task_id": task_id})
        .scalar_one_or_none()
    )
