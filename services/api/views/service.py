"""A job's plan and tasks: views with their task states, tasks with errors, cameras/points, throughput."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, Integer, and_, cast, exists, func, literal_column, select, tuple_
from sqlalchemy.orm import Session

from services.api.jobs.progress import read_counters
from services.api.pagination import PageParams
from services.api.views.compacted import compacted_count, done_states, page_with_compacted
from services.api.views.schemas import PlanSpace, TaskBrief, TaskRead, ThroughputBucket, ViewRead
from services.core.db.compacted import compacted_tasks, cue_filter, has_compacted
from services.core.db.models import (
    JOB_TERMINAL_STATES,
    Camera,
    Job,
    JobSpace,
    Point,
    Space,
    Task,
    TaskState,
    View,
    ViewOutput,
    utcnow,
)
from services.core.domain.cues import CATALOG

MAX_PLAN_ITEMS = 20_000  # cameras or points per space in one plan response
PER_POINT = tuple(n for n, c in CATALOG.items() if c.per_point)
_STATE_ORDER = (TaskState.FAILED, TaskState.RUNNING, TaskState.QUEUED, TaskState.PENDING, TaskState.CANCELLED,
                TaskState.DONE)


def view_state(states: Sequence[str]) -> str:
    """One state for a view from its tasks' states (failed > running > queued > pending > cancelled >
    done)."""
    if not states:
        return TaskState.PENDING
    present = set(states)
    for s in _STATE_ORDER:
        if s in present:
            return s
    return TaskState.PENDING


def _task_of_view(state: str | None = None, cue: str | None = None, not_state: str | None = None):  # type: ignore[no-untyped-def]
    """EXISTS condition: the view has a task (optionally in `state`, of `cue`, or not in `not_state`)."""
    cond = [
        Task.job_id == View.job_id,
        Task.space_id == View.space_id,
        Task.point_idx == View.point_idx,
        Task.view_idx == View.v,
    ]
    if state is not None:
        cond.append(Task.state == state)
    if not_state is not None:
        cond.append(Task.state != not_state)
    if cue is not None:
        cond.append(Task.cue == cue)
    return exists(select(literal_column("1")).select_from(Task).where(and_(*cond)))


def _compacted_view(cue: str | None = None) -> ColumnElement[bool]:
    """EXISTS condition: the view is compacted (and holds a task of `cue`)."""
    cond = [ViewOutput.job_id == View.job_id, ViewOutput.space_id == View.space_id,
            ViewOutput.point_idx == View.point_idx, ViewOutput.view_idx == View.v]
    if cue is not None:
        cond.append(cue_filter(cue))
    return exists(select(literal_column("1")).select_from(ViewOutput).where(and_(*cond)))


def list_views(
    session: Session,
    *,
    job: Job,
    page: PageParams,
    space_id: int | None = None,
    point: int | None = None,
    state: str | None = None,
    cue: str | None = None,
    complete: bool = False,
) -> tuple[list[tuple[View, str, list[Task]]], int]:
    """Views of the job (space, point, v order) with their tasks; filters: a task in `state` (of `cue`),
    complete."""
    cond = [View.job_id == job.id]
    if space_id is not None:
        cond.append(View.space_id == space_id)
    if point is not None:
        cond.append(View.point_idx == point)
    if state is not None or cue is not None:
        has = _task_of_view(state=state, cue=cue)
        # a compacted view's tasks are all done
        cond.append(has | _compacted_view(cue) if state in (None, TaskState.DONE) else has)
    if complete:
        cond.append(_compacted_view() | (_task_of_view() & ~_task_of_view(not_state=TaskState.DONE)))
    total = session.scalar(select(func.count()).select_from(View).where(*cond)) or 0
    rows = session.execute(
        select(View, Space.name)
        .join(Space, Space.id == View.space_id)
        .where(*cond)
        .order_by(View.space_id, View.point_idx, View.v)
        .limit(page.limit)
        .offset(page.offset)
    ).all()
    by_view: dict[tuple[int, int, int], list[Task]] = {}
    if rows:
        keys = [(v.space_id, v.point_idx, v.v) for v, _ in rows]
        point_keys = sorted({(s, p) for s, p, _ in keys})
        tasks = session.scalars(
            select(Task).where(
                Task.job_id == job.id,
                tuple_(Task.space_id, Task.point_idx).in_(point_keys),
            )
        ).all()
        tasks = [*tasks, *compacted_tasks(
            session, job, tuple_(ViewOutput.space_id, ViewOutput.point_idx).in_(point_keys))]
        views_of_point: dict[tuple[int, int], list[int]] = {}
        for s, p, v in keys:
            views_of_point.setdefault((s, p), []).append(v)
        for t in tasks:
            vs = views_of_point.get((t.space_id, t.point_idx), [])
            if t.cue in PER_POINT and t.view_idx == 0:
                # per-point cues live on view 0; show them on every view of the point
                for v in vs:
                    by_view.setdefault((t.space_id, t.point_idx, v), []).append(t)
            elif t.view_idx in vs:
                by_view.setdefault((t.space_id, t.point_idx, t.view_idx), []).append(t)
    out = [(v, name, by_view.get((v.space_id, v.point_idx, v.v), [])) for v, name in rows]
    return out, int(total)


def view_read(view: View, space_name: str, tasks: Sequence[Task]) -> ViewRead:
    """API model of a view and its tasks."""
    order = {n: i for i, n in enumerate(CATALOG)}
    ts = sorted(tasks, key=lambda t: order.get(t.cue, len(order)))
    return ViewRead(
        space_id=view.space_id,
        space=space_name,
        point=view.point_idx,
        view=view.v,
        camera=view.camera_idx,
        fov_deg=math.degrees(view.fov),
        roll_deg=math.degrees(view.roll),
        obliqueness_deg=math.degrees(view.obliqueness),
        resolution=view.resolution,
        world_to_camera=[float(x) for x in view.world_to_camera],
        state=view_state([t.state for t in ts if t.view_idx == view.v or t.cue not in PER_POINT]),
        tasks={t.cue: TaskBrief(id=t.id, state=t.state, attempts=t.attempts, error=t.error) for t in ts},
        outputs=None,
    )


def list_tasks(
    session: Session,
    *,
    job: Job,
    page: PageParams,
    state: str | None = None,
    cue: str | None = None,
    space_id: int | None = None,
) -> tuple[list[Task], int]:
    """Tasks of the job by id, filtered, then the done tasks of compacted views (in view order); the total
    comes from the counters unless a space filter is given."""
    cond = [Task.job_id == job.id]
    compacted = done_states(state) and has_compacted(session, job.id)
    if state is not None:
        cond.append(Task.state == state)
    if cue is not None:
        cond.append(Task.cue == cue)
    if space_id is not None:
        cond.append(Task.space_id == space_id)
        total = int(session.scalar(select(func.count()).select_from(Task).where(*cond)) or 0)
        if compacted:
            total += compacted_count(session, job, cue, space_id)
    else:
        counters = read_counters(session, [job.id])[job.id]
        total = sum(
            n
            for c, states in counters.items()
            if cue is None or c == cue
            for s, n in states.items()
            if state is None or s == state
        )
    if compacted:
        return page_with_compacted(session, job, cond, page, cue, space_id), total
    rows = session.scalars(
        select(Task).where(*cond).order_by(Task.id).limit(page.limit).offset(page.offset)
    ).all()
    return list(rows), total


def task_read(t: Task) -> TaskRead:
    """API model of a task."""
    return TaskRead(
        id=t.id,
        space_id=t.space_id,
        point=t.point_idx,
        view=t.view_idx,
        cue=t.cue,
        state=t.state,
        attempts=t.attempts,
        worker_id=t.worker_id,
        error=t.error,
        output_key=t.output_key,
        size=t.size,
        sha256=t.sha256,
        duration_s=t.duration_s,
        queued_at=t.queued_at,
        started_at=t.started_at,
        finished_at=t.finished_at,
    )


def plan(
    session: Session, *, job: Job, space_id: int | None = None, max_items: int = MAX_PLAN_ITEMS
) -> list[PlanSpace]:
    """Cameras, points and view edges per space of the job (at most `max_items` of each)."""
    q = select(JobSpace.space_id, Space.name, Space.bounds).join(Space, Space.id == JobSpace.space_id)
    q = q.where(JobSpace.job_id == job.id).order_by(JobSpace.position)
    if space_id is not None:
        q = q.where(JobSpace.space_id == space_id)
    out = []
    for sid, name, bounds in session.execute(q).all():
        cams = session.execute(
            select(Camera.x, Camera.y, Camera.z, Camera.yaw)
            .where(Camera.job_id == job.id, Camera.space_id == sid)
            .order_by(Camera.idx)
            .limit(max_items + 1)
        ).all()
        pts = session.execute(
            select(Point.x, Point.y, Point.z, Point.n_views)
            .where(Point.job_id == job.id, Point.space_id == sid)
            .order_by(Point.idx)
            .limit(max_items + 1)
        ).all()
        views = session.execute(
            select(View.point_idx, View.camera_idx)
            .where(View.job_id == job.id, View.space_id == sid)
            .order_by(View.point_idx, View.v)
            .limit(max_items + 1)
        ).all()
        truncated = max(len(cams), len(pts), len(views)) > max_items
        out.append(
            PlanSpace(
                space_id=sid,
                name=name,
                bounds=bounds,
                cameras=[[float(x), float(y), float(z), float(yaw)] for x, y, z, yaw in cams[:max_items]],
                points=[[float(x), float(y), float(z), float(n)] for x, y, z, n in pts[:max_items]],
                views=[[int(p), int(c)] for p, c in views[:max_items]],
                truncated=truncated,
            )
        )
    return out


class _TTLCache:
    """A tiny per-process cache: throughput series are a scan over done tasks, the dashboard polls them."""

    def __init__(self, ttl_s: float = 5.0, max_items: int = 256):
        self.ttl_s, self.max_items = ttl_s, max_items
        self._data: dict[tuple[int, int], tuple[float, tuple[float, list[ThroughputBucket]]]] = {}
        self._lock = threading.Lock()

    def get(self, key: tuple[int, int]) -> tuple[float, list[ThroughputBucket]] | None:
        with self._lock:
            hit = self._data.get(key)
            return hit[1] if hit and time.monotonic() - hit[0] < self.ttl_s else None

    def put(self, key: tuple[int, int], value: tuple[float, list[ThroughputBucket]]) -> None:
        with self._lock:
            if len(self._data) >= self.max_items:
                self._data.clear()
            self._data[key] = (time.monotonic(), value)


_throughput_cache = _TTLCache()


def _bucket_counts(
    session: Session, column: Any, where: list[ColumnElement[bool]], start: datetime,
    bucket_s: float, *extra: Any,
) -> list[tuple[int | None, ...]]:
    """(bucket index, *extra, count) of the rows matching `where` by `column`'s time after `start`."""
    idx: ColumnElement[int]
    if session.get_bind().dialect.name == "postgresql":
        idx = func.floor(func.extract("epoch", column - start) / bucket_s)
    else:  # SQLite stores naive UTC text; julianday works on it (CAST truncates: offsets are >= 0)
        offset_s = (func.julianday(column) - func.julianday(start.replace(tzinfo=None))) * 86400.0
        idx = cast(offset_s / bucket_s, Integer)
    rows = session.execute(
        select(idx.label("k"), *extra, func.count()).where(*where).group_by(literal_column("k"), *extra)
    ).all()
    return [tuple(r) for r in rows]


def throughput(session: Session, *, job: Job, buckets: int = 60) -> tuple[float, list[ThroughputBucket]]:
    """Done tasks per time bucket from task finished_at, `buckets` equal buckets since the job started; a
    compacted view's tasks count at its last task's finish time."""
    cached = _throughput_cache.get((job.id, buckets))
    if cached is not None:
        return cached
    done = [Task.job_id == job.id, Task.state == TaskState.DONE, Task.finished_at.is_not(None)]
    packed = [ViewOutput.job_id == job.id, ViewOutput.finished_at.is_not(None)]
    spans = [session.execute(select(func.min(col), func.max(col)).where(*where)).one()
             for col, where in ((Task.finished_at, done), (ViewOutput.finished_at, packed))]
    firsts, lasts = [a for a, _ in spans if a is not None], [b for _, b in spans if b is not None]
    if not firsts:
        result: tuple[float, list[ThroughputBucket]] = (1.0, [])
        _throughput_cache.put((job.id, buckets), result)
        return result
    first, last = min(firsts), max(lasts)
    start: datetime = job.started_at if job.started_at and job.started_at <= first else first
    end: datetime = max(last, job.finished_at or last) if job.state in JOB_TERMINAL_STATES else utcnow()
    span = max((end - start).total_seconds(), 1.0)
    bucket_s = max(1.0, math.ceil(span / buckets))
    counts: dict[int, int] = {}
    for k, n in _bucket_counts(session, Task.finished_at, done, start, bucket_s):
        if k is not None:
            counts[int(k)] = counts.get(int(k), 0) + int(n or 0)
    for k, mask, n in _bucket_counts(
        session, ViewOutput.finished_at, packed, start, bucket_s, ViewOutput.cue_mask
    ):
        if k is not None:
            counts[int(k)] = counts.get(int(k), 0) + int(mask or 0).bit_count() * int(n or 0)
    n_buckets = max(int(span // bucket_s) + 1, max(counts, default=-1) + 1)
    series = [
        ThroughputBucket(t=start + timedelta(seconds=i * bucket_s), done=counts.get(i, 0))
        for i in range(n_buckets)
    ]
    result = (bucket_s, series)
    _throughput_cache.put((job.id, buckets), result)
    return result
