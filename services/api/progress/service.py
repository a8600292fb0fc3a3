"""Server-sent progress events: poll the counters every ~0.5 s, send a job only when its counts or state change.

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
from typing import Any

import anyio
from fastapi import Request
from sqlalchemy import select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, load_only

from services.api.jobs.service import job_event
from services.api.progress.compute import Counters, read_counters
from services.api.progress.rates import RateTracker
from services.core.db.models import JOB_TERMINAL_STATES, Job

log = logging.getLogger("omnidata.api")

MAX_JOBS_PER_STREAM = 500  # /events follows the caller's most recent jobs
_JOB_COLUMNS = (Job.id, Job.owner, Job.name, Job.state, Job.error, Job.started_at, Job.finished_at, Job.created_at)


@dataclass
class Snapshot:
    """Last state a stream has sent: per job, a fingerprint and the counters read."""

    fingerprints: dict[int, str] = field(default_factory=dict)
    counters: dict[int, Counters] = field(default_factory=dict)
    states: dict[int, str] = field(default_factory=dict)


def _fingerprint(job: Job, counters: Counters) -> str:
    return json.dumps([job.state, job.error, counters], sort_keys=True)


def poll_jobs(
    session: Session, *, owner: str, job_id: int | None, snap: Snapshot, rates: RateTracker
) -> tuple[list[dict[str, Any]], list[int]]:
    """Changed jobs since `snap` (as JSON-ready dicts) and ids of deleted ones; updates `snap`."""
    q = select(Job).options(load_only(*_JOB_COLUMNS)).where(Job.owner == owner)
    if job_id is not None:
        q = q.where(Job.id == job_id)
    else:
        q = q.order_by(Job.id.desc()).limit(MAX_JOBS_PER_STREAM)
    jobs = list(session.scalars(q).all())
    # Counters of finished jobs do not move (unless a retry makes the job run again, which changes its state).
    stale = [
        j.id
        for j in jobs
        if j.id not in snap.counters or j.state not in JOB_TERMINAL_STATES or snap.states.get(j.id) != j.state
    ]
    fresh = read_counters(session, stale)
    changed: list[dict[str, Any]] = []
    for j in jobs:
        counters = fresh.get(j.id, snap.counters.get(j.id, {}))
        fp = _fingerprint(j, counters)
        snap.counters[j.id] = counters
        snap.states[j.id] = j.state
        if snap.fingerprints.get(j.id) != fp:
            snap.fingerprints[j.id] = fp
            changed.append(job_event(j, counters, rates).model_dump(mode="json"))
    seen = {j.id for j in jobs}
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
    session.rollback()  # end the read transaction: the next poll must see new commits
    return changed, deleted


def sse(event: str, data: Any, ident: int | None = None) -> str:
    """One server-sent event."""
    head = f"id: {ident}\n" if ident is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


async def event_stream(
    request: Request,
    poll: Callable[[Snapshot], tuple[list[dict[str, Any]], list[int]]],
    *,
    poll_s: float,
    heartbeat_s: float,
    stop_when_gone: bool = False,
    stop_when_final: bool = False,
) -> AsyncIterator[str]:
    """Yield SSE text: `job` events for changed jobs, `deleted` for removed ones, heartbeat comments.

    `stop_when_final`: once every followed job is in a final state (done, failed, cancelled), send an `end`
    event ({"id", "state"}; EventSource clients close on it instead of reconnecting) and close the stream.
    """
    snap = Snapshot()
    seq = 0
    yield "retry: 2000\n: connected\n\n"
    last_sent = time.monotonic()
    while True:
        if await request.is_disconnected():
            return
        try:
            changed, deleted = await anyio.to_thread.run_sync(poll, snap)
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
