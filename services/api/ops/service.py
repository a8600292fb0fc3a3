"""Readiness checks (database, broker, storage) and Prometheus metrics built from the database and Redis.

Metrics come from the progress counters (tasks by state, dispatch and completion counts), Redis LLEN of the
queues, worker heartbeats, and one aggregate over task durations for the histogram; the whole text is
cached for a few seconds so frequent scrapes of a 1M-task database stay cheap.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from typing import TypeVar

import redis as redis_lib
from fastapi import FastAPI
from sqlalchemy import Select, case, func, select, text
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import InstrumentedAttribute, Session

from services.core.db.durations import DURATION_BUCKETS_S
from services.core.db.engine import SchemaNotCurrent, schema_problem
from services.core.db.jobs import HELD_SUFFIX, storage_held_jobs
from services.core.db.models import (
    JOB_STATES,
    TASK_STATES,
    CompactedDuration,
    Job,
    JobCounter,
    Task,
    TaskState,
    Worker,
    utcnow,
)
from services.core.storage import StorageUnavailable

CHECK_TIMEOUT_S = 3.0
METRICS_TTL_S = 5.0
STORAGE_PROBE_TTL_S = 5.0
_metrics_lock = threading.Lock()


def redis_client(app: FastAPI) -> redis_lib.Redis | None:
    """The app's Redis client for the broker URL (None when the broker is not Redis)."""
    url: str = app.state.settings.broker_url
    if not url.startswith(("redis://", "rediss://", "unix://")):
        return None
    if app.state.redis is None:
        app.state.redis = redis_lib.Redis.from_url(url, socket_timeout=2.0, socket_connect_timeout=2.0)
    client: redis_lib.Redis = app.state.redis
    return client


@dataclass
class Check:
    """Outcome of one readiness check."""

    ok: bool
    latency_ms: float
    error: str | None = None
    skipped: bool = False


async def _run(fn: Callable[[], object]) -> Check:
    t0 = time.perf_counter()
    try:
        await asyncio.wait_for(asyncio.to_thread(fn), timeout=CHECK_TIMEOUT_S)
        return Check(ok=True, latency_ms=round((time.perf_counter() - t0) * 1000, 2))
    except TimeoutError:
        return Check(
            False, round((time.perf_counter() - t0) * 1000, 2), f"no answer within {CHECK_TIMEOUT_S:.0f} s"
        )
    except Exception as e:  # any failure of a dependency means "not ready", with the reason
        return Check(False, round((time.perf_counter() - t0) * 1000, 2), f"{type(e).__name__}: {e}"[:300])


async def _storage_check(app: FastAPI) -> Check:
    """The store's probe (a write and a delete; a folder's free space), then whether jobs wait for the store
    (a worker's outputs refused since: a 5xx on big writes only, a full disk the probe's bytes still fit on),
    at most once per STORAGE_PROBE_TTL_S: /ready needs no token."""
    last: tuple[float, Check] | None = app.state.storage_probe
    if last is not None and time.monotonic() - last[0] < STORAGE_PROBE_TTL_S:
        return last[1]

    def probe() -> None:
        app.state.store.probe()
        try:
            with app.state.read_sessionmaker() as session:
                held = storage_held_jobs(session)
        except SQLAlchemyError:  # the database check reports that
            return
        if held:
            problem = (held[0][1] or "").removesuffix(HELD_SUFFIX)
            raise StorageUnavailable(f"{problem} ({len(held)} job(s) wait for the store)")

    check = await _run(probe)
    app.state.storage_probe = (time.monotonic(), check)
    return check


async def readiness(app: FastAPI) -> dict[str, Check]:
    """Check the database (SELECT 1, then its schema revision), the broker (Redis PING) and the object store
    (bucket there and writable), concurrently."""

    def db() -> None:
        with app.state.engine.connect() as conn:
            conn.execute(text("SELECT 1"))

    def schema() -> None:
        problem = schema_problem(app.state.engine, app.state.schema_heads)
        if problem:
            raise SchemaNotCurrent(problem)

    client = redis_client(app)

    def broker() -> None:
        assert client is not None
        if not client.ping():
            raise ConnectionError("PING was not answered with PONG")

    names = ["database", "storage"] + (["broker"] if client is not None else [])
    runs = [_run(db), _storage_check(app)] + ([_run(broker)] if client is not None else [])
    results = await asyncio.gather(*runs)
    checks = dict(zip(names, results, strict=True))
    if client is None:
        checks["broker"] = Check(ok=True, latency_ms=0.0, skipped=True)
    # An unreachable database is reported once (database), not again as a schema failure.
    checks["schema"] = (
        await _run(schema)
        if checks["database"].ok
        else Check(False, 0.0, "database unreachable", skipped=True)
    )
    return checks


# ---------------------------------------------------------------------------------------------- metrics


def _esc(v: str) -> str:
    return v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _fmt(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else repr(float(v))


class _Text:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def family(self, name: str, kind: str, help_text: str) -> None:
        self.lines.append(f"# HELP {name} {help_text}")
        self.lines.append(f"# TYPE {name} {kind}")

    def sample(self, name: str, value: float, **labels: str) -> None:
        lab = ",".join(f'{k}="{_esc(v)}"' for k, v in labels.items())
        self.lines.append(f"{name}{{{lab}}} {_fmt(value)}" if lab else f"{name} {_fmt(value)}")

    def render(self) -> str:
        return "\n".join(self.lines) + "\n"


def queue_depths(app: FastAPI) -> dict[str, int | None]:
    """LLEN of the render and derive queues (None when Redis cannot be reached or is not the broker)."""
    settings = app.state.settings
    queues = [settings.queue_render, settings.queue_derive]
    client = redis_client(app)
    if client is None:
        return dict.fromkeys(queues)
    try:
        pipe = client.pipeline()
        for q in queues:
            pipe.llen(q)
        return {q: int(n) for q, n in zip(queues, pipe.execute(), strict=True)}
    except redis_lib.RedisError:
        return dict.fromkeys(queues)


_Cols = TypeVar("_Cols", bound=tuple[object, ...])


def _owned(
    stmt: Select[_Cols], owner: str | None, job_id: InstrumentedAttribute[int] | None = None
) -> Select[_Cols]:
    """`stmt` limited to the jobs of `owner` (None: every job), joining Job on the `job_id` column if
    given."""
    if owner is None:
        return stmt
    if job_id is not None:
        stmt = stmt.join(Job, Job.id == job_id)
    return stmt.where(Job.owner == owner)


def _durations(session: Session, owner: str | None) -> dict[str, tuple[list[int], int, float]]:
    """cue -> (cumulative bucket counts, count, sum) of done tasks' run times: task rows plus compacted
    tasks."""
    cols = [func.sum(case((Task.duration_s <= b, 1), else_=0)) for b in DURATION_BUCKETS_S]
    rows = session.execute(
        _owned(select(Task.cue, *cols, func.count(), func.sum(Task.duration_s)), owner, Task.job_id)
        .where(Task.state == TaskState.DONE, Task.duration_s.is_not(None))
        .group_by(Task.cue)
    ).all()
    hist: dict[str, tuple[list[int], int, float]] = {
        str(r[0]): (
            [int(c or 0) for c in r[1 : 1 + len(DURATION_BUCKETS_S)]], int(r[-2]), float(r[-1] or 0.0),
        )
        for r in rows
    }
    d = CompactedDuration
    packed = session.execute(
        _owned(select(d.cue, d.bucket, func.sum(d.n), func.sum(d.sum_s)), owner, d.job_id).group_by(
            d.cue, d.bucket
        )
    ).all()
    for cue, bucket, n, total_s in packed:
        counts, count, total = hist.get(str(cue), ([0] * len(DURATION_BUCKETS_S), 0, 0.0))
        # cumulative: le >= bucket
        counts = [c + (int(n) if int(bucket) <= i else 0) for i, c in enumerate(counts)]
        hist[str(cue)] = (counts, count + int(n), total + float(total_s or 0.0))
    return hist


def build_metrics(session: Session, app: FastAPI, owner: str | None = None) -> str:
    """The Prometheus text exposition of the service's state; `owner` limits tasks and jobs to one tenant's
    (and leaves out the broker queues, which carry every tenant's work)."""
    out = _Text()
    scope = "all jobs" if owner is None else "the caller's jobs"
    by_state = dict.fromkeys(TASK_STATES, 0)
    counters = _owned(select(JobCounter.state, func.sum(JobCounter.n)), owner, JobCounter.job_id).group_by(
        JobCounter.state
    )
    for state, n in session.execute(counters):
        by_state[state] = int(n or 0)
    out.family("omnidata_tasks", "gauge", f"Tasks by state over {scope} (from the progress counters).")
    for s in TASK_STATES:
        out.sample("omnidata_tasks", by_state.get(s, 0), state=s)

    jobs = dict.fromkeys(JOB_STATES, 0)
    for state, n in session.execute(_owned(select(Job.state, func.count()), owner).group_by(Job.state)):
        jobs[state] = int(n)
    out.family("omnidata_jobs", "gauge", "Jobs by state.")
    for s in JOB_STATES:
        out.sample("omnidata_jobs", jobs.get(s, 0), state=s)

    dispatched = sum(
        by_state[s] for s in (TaskState.QUEUED, TaskState.RUNNING, TaskState.DONE, TaskState.FAILED)
    )
    out.family(
        "omnidata_tasks_dispatched_total", "counter",
        "Tasks handed to the broker at least once (existing jobs).",
    )
    out.sample("omnidata_tasks_dispatched_total", dispatched)
    out.family("omnidata_tasks_completed_total", "counter", "Tasks that finished, by result (existing jobs).")
    out.sample("omnidata_tasks_completed_total", by_state[TaskState.DONE], result="done")
    out.sample("omnidata_tasks_completed_total", by_state[TaskState.FAILED], result="failed")

    if owner is None:
        out.family(
            "omnidata_queue_depth", "gauge", "Messages waiting in a broker queue (Redis LLEN); -1 if unknown."
        )
        for q, n in queue_depths(app).items():
            out.sample("omnidata_queue_depth", -1 if n is None else n, queue=q)

    stale_s = app.state.settings.heartbeat_timeout_s  # the reaper's "dead" age, as /workers uses
    cutoff = utcnow() - timedelta(seconds=stale_s)
    alive = (
        session.scalar(select(func.count()).select_from(Worker).where(Worker.last_heartbeat >= cutoff)) or 0
    )
    total_workers = session.scalar(select(func.count()).select_from(Worker)) or 0
    out.family("omnidata_workers", "gauge", f"Workers by heartbeat (alive: within {stale_s:.0f} s).")
    out.sample("omnidata_workers", alive, status="alive")
    out.sample("omnidata_workers", total_workers - alive, status="stale")

    out.family("omnidata_task_duration_seconds", "histogram", "Run time of finished tasks, by cue.")
    for cue, (counts, n, total_s) in sorted(_durations(session, owner).items()):
        for b, c in zip(DURATION_BUCKETS_S, counts, strict=True):
            out.sample("omnidata_task_duration_seconds_bucket", c, cue=cue, le=_fmt(b))
        out.sample("omnidata_task_duration_seconds_bucket", n, cue=cue, le="+Inf")
        out.sample("omnidata_task_duration_seconds_sum", total_s, cue=cue)
        out.sample("omnidata_task_duration_seconds_count", n, cue=cue)
    return out.render()


def cached_metrics(app: FastAPI, owner: str | None = None) -> str:
    """build_metrics for `owner` (None: service-wide), reused for METRICS_TTL_S seconds (one builder at a
    time)."""
    cache: dict[str | None, tuple[float, str]] = app.state.metrics_cache  # owner -> (built at, text)
    with _metrics_lock:
        hit = cache.get(owner)
        if hit is not None and time.monotonic() - hit[0] < METRICS_TTL_S:
            return str(hit[1])
        with app.state.read_sessionmaker() as session:
            body = build_metrics(session, app, owner)
        cache[owner] = (time.monotonic(), body)
        return body
