"""Compaction: the task rows of finished views replaced by one `view_output` row per view.

A view whose every task is done (its ~18 rows, the internal `passes` task included) and whose last task
finished more than `compact_after_s` ago is packed (services.core.db.view_outputs) into one row, in one
transaction per chunk of views: its task rows are deleted (DELETE ... RETURNING, so a task that left `done`
meanwhile, a resume, makes the chunk roll back) and the compact rows inserted. The job_counter counters are
left alone: the done counts still count these tasks, which is what they are.

Each job is walked in the order of its unique index (space, point, view, cue) from a cursor kept in memory, a
chunk of rows at a time, for at most `compact_pass_s` a pass. Deleted rows leave the index, so the next walk
from the start skips them; a chunk of a running job with no done row at all, or with finished views but none
due yet, sends the cursor back to the start (dispatch runs oldest first, so the views after it have not run,
or finished later). A terminal job whose whole walk compacted nothing is not walked again until its state
changes.

A pass that walked every job to its end (not cut short by `compact_pass_s`) knows when the next view can be
due: the earliest finished-but-not-due view's last finish plus `compact_after_s`, and no sooner than
`compact_after_s` from now for everything still running. Passes before then do nothing, so a job whose views
are not due is not re-read every second (a 66-view `generate` read its 1,210 rows 40 times: 3% of its CPU).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import delete, insert, select, text, tuple_
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.compacted import space_names
from services.core.db.durations import add_durations
from services.core.db.models import JOB_TERMINAL_STATES, Job, JobState, Task, TaskState, ViewOutput, utcnow
from services.core.db.view_outputs import DoneTask, cue_mask, keys_of, pack

log = logging.getLogger(__name__)

# task rows read (~110 views compacted) per transaction: a chunk is ~0.1 s of scheduler CPU
CHUNK_ROWS = 2_000
COMPACTED_STATES = (JobState.RUNNING, JobState.PAUSED, JobState.DONE, JobState.FAILED, JobState.CANCELLED)
_COLUMNS = (Task.space_id, Task.point_idx, Task.view_idx, Task.cue, Task.id, Task.state, Task.attempts,
            Task.output_key, Task.size, Task.sha256, Task.duration_s, Task.finished_at)

ViewKey = tuple[int, int, int]


@dataclass
class CompactionResult:
    """What a pass did."""

    views: int = 0
    tasks: int = 0
    chunks: int = 0
    seconds: float = 0.0


@dataclass
class _Walk:
    cursor: tuple[int, int, int] = (-1, -1, -1)  # last (space, point, view) looked at
    compacted: int = 0  # views compacted since the walk last started from the beginning


@dataclass
class Compactor:
    """Compacts finished views of every job, a bounded amount per `run_once` (one per scheduler)."""

    sessionmaker: sessionmaker[Session]
    after_s: float = 60.0
    pass_s: float = 0.2
    chunk_rows: int = CHUNK_ROWS
    _walks: dict[int, _Walk] = field(default_factory=dict)
    _settled: dict[int, str] = field(default_factory=dict)  # terminal job -> the state its last walk ended in
    # no view can be due before this (set by a pass that walked everything)
    _idle_until: datetime | None = None
    _next_due: datetime | None = None  # earliest due time of a finished view seen by this pass

    def run_once(self, now: datetime | None = None) -> CompactionResult:
        """Compact finished views for at most `pass_s` seconds (at least one chunk when there is work)."""
        t0 = time.perf_counter()
        res = CompactionResult()
        now = now or utcnow()
        if self._idle_until is not None and now < self._idle_until:
            return res
        self._next_due = now + timedelta(seconds=self.after_s)  # a view finishing from now on
        with self.sessionmaker() as s:
            jobs = [(int(j), str(st)) for j, st in s.execute(
                select(Job.id, Job.state).where(Job.state.in_(COMPACTED_STATES)).order_by(Job.id))]
        live = {j for j, _ in jobs}
        for gone in [j for j in self._walks if j not in live]:
            self._walks.pop(gone, None)
        self._settled = {j: st for j, st in self._settled.items() if j in live}
        for job_id, state in jobs:
            if self._settled.get(job_id) == state:
                continue
            self._settled.pop(job_id, None)
            while time.perf_counter() - t0 < self.pass_s or not res.chunks:
                views, tasks, more = self.compact_chunk(job_id, state, now)
                res.views += views
                res.tasks += tasks
                res.chunks += 1
                if not more:
                    break
            if time.perf_counter() - t0 >= self.pass_s:
                break
        res.seconds = time.perf_counter() - t0
        self._idle_until = None if res.seconds >= self.pass_s else self._next_due
        return res

    def compact_chunk(self, job_id: int, state: str, now: datetime | None = None) -> tuple[int, int, bool]:
        """Compact the finished views of one chunk of the job's rows after its cursor; (views, tasks, more to
        walk in this pass). Commits."""
        walk = self._walks.setdefault(job_id, _Walk())
        cutoff = (now or utcnow()) - timedelta(seconds=self.after_s)
        with self.sessionmaker() as s:
            if s.get_bind().dialect.name == "postgresql":
                # The planner underestimates the rows after a row-value cursor and would read every remaining
                # row of the job (bitmap scan) and sort them, per chunk; the unique index gives them in order.
                s.execute(text("SET LOCAL enable_bitmapscan = off"))
                s.execute(text("SET LOCAL enable_sort = off"))
            rows = s.execute(
                select(*_COLUMNS)
                .where(
                    Task.job_id == job_id, tuple_(Task.space_id, Task.point_idx, Task.view_idx) > walk.cursor
                )
                .order_by(Task.space_id, Task.point_idx, Task.view_idx, Task.cue)
                .limit(self.chunk_rows)
            ).all()
            end = len(rows) < self.chunk_rows
            views = _group(rows, complete_only=not end)
            # one view bigger than a chunk cannot happen (<= 255 tasks); an empty job has no rows
            if not views:
                return self._restart(job_id, state, walk), 0, False
            walk.cursor = max(views)
            if not end and state == JobState.RUNNING and all(r.state != TaskState.DONE for r in rows):
                walk.cursor = (-1, -1, -1)  # the rest of a running job has not run yet
                return 0, 0, False
            ready = {k: v for k, v in views.items() if _finished(v, cutoff)}
            self._note_due(v for k, v in views.items() if k not in ready)
            if (
                not ready
                and not end
                and state == JobState.RUNNING
                and any(_finished(v, None) for v in views.values())
            ):
                # views finish about in walk order: after a chunk of views done but not due, the rest is not
                # due either (walking it anew every pass cost ~8 us of CPU a row: 60 s of a fleet's views a
                # second)
                walk.cursor = (-1, -1, -1)
                return 0, 0, False
            n_views, n_tasks = _compact(s, job_id, ready) if ready else (0, 0)
            s.commit()
        walk.compacted += n_views
        if end:
            self._restart(job_id, state, walk)
        return n_views, n_tasks, not end

    def _note_due(self, waiting: Iterable[Sequence[Any]]) -> None:
        """Lower `_next_due` to the due time of each finished view among `waiting` (not due yet)."""
        for rows in waiting:
            if _finished(rows, None):
                last = max((r.finished_at for r in rows if r.finished_at is not None), default=None)
                if last is not None:
                    due = last + timedelta(seconds=self.after_s)
                    if self._next_due is None or due < self._next_due:
                        self._next_due = due

    def _restart(self, job_id: int, state: str, walk: _Walk) -> int:
        # a terminal job walked to its end without compacting anything has nothing left to compact
        if walk.compacted == 0 and state in JOB_TERMINAL_STATES:
            self._settled[job_id] = state
        walk.cursor, walk.compacted = (-1, -1, -1), 0
        return 0


def _group(rows: Sequence[Any], *, complete_only: bool) -> dict[ViewKey, list[Any]]:
    """Rows by view; the last view of a full chunk may be cut short, so it waits for the next chunk."""
    views: dict[ViewKey, list[Any]] = {}
    for r in rows:
        views.setdefault((int(r.space_id), int(r.point_idx), int(r.view_idx)), []).append(r)
    if complete_only and len(views) > 1:
        views.pop(max(views))
    return views


def _finished(rows: Sequence[Any], cutoff: datetime | None) -> bool:
    """Every task of the view done, the last one before `cutoff` (None: whenever)."""
    if any(r.state != TaskState.DONE for r in rows):
        return False
    if cutoff is None:
        return True
    last = max((r.finished_at for r in rows if r.finished_at is not None), default=None)
    return last is None or last <= cutoff


_DELETE_PG = text("DELETE FROM task WHERE id = ANY(CAST(:ids AS bigint[])) AND state = 'done' RETURNING id")


def _delete_done(s: Session, ids: list[int]) -> set[int]:
    """Delete the tasks of `ids` that are still done; the ids deleted. (Postgres: one array parameter, as the
    driver's rewriting of thousands of IN parameters cost more CPU than the delete itself.)"""
    if s.get_bind().dialect.name == "postgresql":
        return {int(x) for x in s.scalars(_DELETE_PG, {"ids": ids})}
    deleted: set[int] = set()
    for i in range(0, len(ids), 5_000):
        part = ids[i : i + 5_000]
        deleted.update(int(x) for x in s.scalars(
            delete(Task).where(Task.id.in_(part), Task.state == TaskState.DONE).returning(Task.id)
            .execution_options(synchronize_session=False)))
    return deleted


def _compact(s: Session, job_id: int, views: dict[ViewKey, list[Any]]) -> tuple[int, int]:
    """Delete the views' task rows (only those still done) and insert their packed rows; in the caller's
    transaction, rolled back (and nothing compacted) when a task moved meanwhile."""
    job = s.get(Job, job_id)
    assert job is not None
    names = space_names(s, job_id)
    ids = [int(r.id) for rows in views.values() for r in rows]
    # a resume took some back meanwhile: leave this chunk to a later pass
    if len(_delete_done(s, ids)) != len(ids):
        s.rollback()
        return 0, 0
    compact = []
    for (space_id, point, view), rows in views.items():
        tasks = [
            DoneTask(
                int(r.id), str(r.cue), int(r.attempts), r.output_key, r.size, r.sha256, r.duration_s,
                r.finished_at,
            )
            for r in rows
        ]
        name = names[space_id]
        compact.append({
            "job_id": job_id, "space_id": space_id, "point_idx": point, "view_idx": view,
            "cue_mask": cue_mask(t.cue for t in tasks),
            "finished_at": max((t.finished_at for t in tasks if t.finished_at is not None), default=None),
            "outputs": pack(tasks, keys_of(job, name, point, view)),
        })
    s.execute(insert(ViewOutput), compact)
    add_durations(s, job_id, [(str(r.cue), r.duration_s) for rows in views.values() for r in rows])
    return len(views), len(ids)
