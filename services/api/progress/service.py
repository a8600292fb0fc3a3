"""Server-sent progress events: poll the counters every ~0.5 s, send a job only when its counts or state
change.

Each SSE connection polls in a worker thread with a short-lived session, so no connection is held between
polls. Change detection ignores throughput/ETA (they drift with the clock) and compares state, error and
counter values; a comment line is sent as a heartbeat when nothing changed for a while, which keeps proxies
from closing the connection and lets the server notice a gone client.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from datetime import datetime
from typing import cast

import anyio
from fastapi import Request
from sqlalchemy import select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, load_only

from services.api.jobs.progress import Counters, read_counters
from services.api.jobs.rates import RateTracker
from services.api.jobs.service import job_event
from services.core.db.models import JOB_TERMINAL_STATES, Job
from services.core.domain.json_types import JSONObject

log = logging.getLogger("omnidata.api")

MAX_JOBS_PER_STREAM = 500  # /events follows the caller's most recent jobs
_JOB_COLUMNS = (
    Job.id, Job.owner, Job.name, Job.state, Job.error, Job.started_at, Job.finished_at, Job.created_at,
)


@dataclass
class Snapshot:
    """Last state a stream has sent: per job, a fingerprint and the counters read."""

    fingerprints: dict[int, str] = field(default_factory=dict)
    counters: dict[int, Counters] = field(default_factory=dict)
    states: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True)
class JobRow:
    """The columns of a job an event needs, detached from any session (shared between streams' threads)."""

    id: int
    owner: str
    name: str
    state: str
    error: str | None
    started_at: datetime | None
    finished_at: datetime | None
    created_at: datetime


# job id -> ((state, finished_at) when read, its counters): finished jobs' counters, kept between reads
FinalCounters = dict[int, tuple[tuple[str, datetime | None], Counters]]


@dataclass(frozen=True)
class JobsRead:
    """One read of a tenant's followed jobs: rows (newest first) and every listed job's counters."""

    jobs: list[JobRow]
    counters: dict[int, Counters]


def read_jobs(
    session: Session, *, owner: str, job_id: int | None, final: FinalCounters | None = None,
) -> JobsRead:
    """The jobs a stream follows and their counters. `final` remembers counters of finished jobs (keyed by the
    job's state and finish time: a retried job that finishes again is read again) and is updated in place."""
    q = select(Job).options(load_only(*_JOB_COLUMNS)).where(Job.owner == owner)
    if job_id is not None:
        q = q.where(Job.id == job_id)
    else:
        q = q.order_by(Job.id.desc()).limit(MAX_JOBS_PER_STREAM)
    jobs = [JobRow(j.id, j.owner, j.name, j.state, j.error, j.started_at, j.finished_at, j.created_at)
            for j in session.scalars(q).all()]
    session.rollback()  # end the read transaction: the next poll must see new commits
    final = final if final is not None else {}
    # Counters of finished jobs do not move (unless a retry makes the job run again, which changes its state).
    known = {
        j.id: final[j.id][1]
        for j in jobs
        if j.state in JOB_TERMINAL_STATES and j.id in final and final[j.id][0] == (j.state, j.finished_at)
    }
    fresh = read_counters(session, [j.id for j in jobs if j.id not in known])
    session.rollback()
    counters = {j.id: known.get(j.id, fresh.get(j.id, {})) for j in jobs}
    final.clear()
    final.update(
        {j.id: ((j.state, j.finished_at), counters[j.id]) for j in jobs if j.state in JOB_TERMINAL_STATES}
    )
    return JobsRead(jobs, counters)


def diff_jobs(
    read: JobsRead, *, job_id: int | None, snap: Snapshot, rates: RateTracker
) -> tuple[list[JSONObject], list[int]]:
    """Changed jobs since `snap` (as JSON-ready dicts) and ids of deleted ones; updates `snap`."""
    changed: list[JSONObject] = []
    for j in read.jobs:
        counters = read.counters.get(j.id, {})
        fp = json.dumps([j.state, j.error, counters], sort_keys=True)
        snap.counters[j.id] = counters
        snap.states[j.id] = j.state
        if snap.fingerprints.get(j.id) != fp:
            snap.fingerprints[j.id] = fp
            changed.append(job_event(cast(Job, j), counters, rates).model_dump(mode="json"))
    seen = {j.id for j in read.jobs}
    oldest = min(seen) if seen else None
    deleted = []
    for jid in list(snap.fingerprints):
        if jid in seen:
            continue
        # a job that merely fell out of the "most recent" window is not reported as deleted
        if job_id is not None or (oldest is not None and jid > oldest) or not seen:
            deleted.append(jid)
        for d in (snap.fingerprints, snap.counters, snap.states):
            d.pop(jid, None)
    return changed, deleted


def poll_jobs(
    session: Session, *, owner: str, job_id: int | None, snap: Snapshot, rates: RateTracker
) -> tuple[list[JSONObject], list[int]]:
    """Changed jobs since `snap` (as JSON-ready dicts) and ids of deleted ones; updates `snap`."""
    return diff_jobs(read_jobs(session, owner=owner, job_id=job_id), job_id=job_id, snap=snap, rates=rates)


def sse(event: str, data: object, ident: int | None = None) -> str:
    """One server-sent event."""
    head = f"id: {ident}\n" if ident is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


async def event_stream(
    request: Request,
    poll: Callable[[Snapshot], tuple[list[JSONObject], list[int]]],
    *,
    poll_s: float,
    heartbeat_s: float,
    stop_when_gone: bool = False,
    stop_when_final: bool = False,
    limiter: anyio.CapacityLimiter | None = None,
) -> AsyncIterator[str]:
    """Yield SSE text: `job` events for changed jobs, `deleted` for removed ones, heartbeat comments.

    `stop_when_final`: once every followed job is in a final state (done, failed, cancelled), send an `end`
    event ({"id", "state"}; EventSource clients close on it instead of reconnecting) and close the stream.
    Polls run in worker threads under `limiter` (default: anyio's pool, shared with the synchronous routes).
    """
    snap = Snapshot()
    seq = 0
    yield "retry: 2000\n: connected\n\n"
    last_sent = time.monotonic()
    while True:
        if await request.is_disconnected():
            return
        try:
            changed, deleted = await anyio.to_thread.run_sync(poll, snap, limiter=limiter)
        except OperationalError as e:  # database restarting: keep the stream, try again next tick
            log.warning("SSE poll failed: %s", e)
            yield ": database unavailable, retrying\n\n"
            await anyio.sleep(max(poll_s, 1.0))
            continue
        for payload in changed:
            seq += 1
            yield sse("job", payload, seq)
        for jid in deleted:
            seq += 1
            yield sse("deleted", {"id": jid}, seq)
        if changed or deleted:
            last_sent = time.monotonic()
        elif time.monotonic() - last_sent >= heartbeat_s:
            yield f": heartbeat {int(time.time())}\n\n"
            last_sent = time.monotonic()
        if stop_when_gone and deleted:
            return
        if stop_when_final and snap.states and all(st in JOB_TERMINAL_STATES for st in snap.states.values()):
            for jid, st in snap.states.items():
                seq += 1
                yield sse("end", {"id": jid, "state": st}, seq)
            return
        await anyio.sleep(poll_s)
