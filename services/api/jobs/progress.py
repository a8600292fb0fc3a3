"""A job's progress from its counter rows: totals per state and cue, fraction, throughput and ETA.

Only the job's handful of `job_counter` rows are read, so progress costs the same on a 1M-task job as on a
10-task one. Throughput comes from RateTracker, falling back to the average since the job started.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime

from sqlalchemy.orm import Session

from services.api.jobs.rates import RateTracker
from services.api.jobs.schemas import CueProgress, Progress
from services.core.db.counters import summed_counters
from services.core.db.models import (
    JOB_TERMINAL_STATES,
    TASK_ACTIVE_STATES,
    TASK_STATES,
    TASK_TERMINAL_STATES,
    Job,
    JobState,
    TaskState,
    utcnow,
)
from services.core.domain.cues import CATALOG

FINISHED_STATES = TASK_TERMINAL_STATES


REMAINING_STATES = TASK_ACTIVE_STATES


Counters = dict[str, dict[str, int]]  # cue -> state -> n


STALL_MIN_S = 10.0  # a running job that finished nothing for this long, and ...


STALL_INTERVALS = 5.0  # ... for this many of its mean intervals between finishes, has no ETA


_CUE_ORDER = {name: i for i, name in enumerate(CATALOG)}


def read_counters(session: Session, job_ids: Sequence[int]) -> dict[int, Counters]:
    """Counters of several jobs in one query: {job_id: {cue: {state: n}}} (zero rows omitted)."""
    out: dict[int, Counters] = {j: {} for j in job_ids}
    if not job_ids:
        return out
    rows = session.execute(summed_counters(list(job_ids)))  # the counter shards, summed
    for job_id, cue, state, n in rows:
        out[int(job_id)].setdefault(cue, {})[state] = int(n)
    return out


def _by_state(counts: dict[str, int]) -> dict[str, int]:
    return {s: int(counts.get(s, 0)) for s in TASK_STATES}


def compute_progress(
    job: Job, counters: Counters, rates: RateTracker | None, now: datetime | None = None
) -> tuple[Progress, dict[str, CueProgress]]:
    """Overall and per-cue progress of `job` from its counters; throughput and ETA from `rates`."""
    totals: dict[str, int] = dict.fromkeys(TASK_STATES, 0)
    cues: dict[str, CueProgress] = {}
    labels_done = 0
    for cue in sorted(counters, key=lambda c: _CUE_ORDER.get(c, len(_CUE_ORDER))):
        by = _by_state(counters[cue])
        total = sum(by.values())
        fin = sum(by[s] for s in FINISHED_STATES)
        for s, n in by.items():
            totals[s] += n
        if cue in CATALOG and not CATALOG[cue].internal:
            labels_done += by[TaskState.DONE]
        cues[cue] = CueProgress(
            by_state=by, total=total, done=by[TaskState.DONE], fraction=fin / total if total else 0.0
        )
    total = sum(totals.values())
    finished = sum(totals[s] for s in FINISHED_STATES)
    remaining = sum(totals[s] for s in REMAINING_STATES)
    if total:
        fraction = finished / total
    else:
        fraction = 1.0 if job.state == JobState.DONE else 0.0

    rate: float | None = None
    label_rate: float | None = None
    recent = (
        rates.observe(job.id, finished, labels_done)
        if rates is not None and job.state == JobState.RUNNING
        else None
    )
    if recent is not None:
        rate, label_rate = recent
    elif job.started_at is not None and finished:
        end = job.finished_at if job.state in JOB_TERMINAL_STATES and job.finished_at else (now or utcnow())
        span = (end - job.started_at).total_seconds()
        if span > 0:
            rate, label_rate = finished / span, labels_done / span
    eta: float | None = None
    if job.state in JOB_TERMINAL_STATES:
        eta = 0.0 if job.state == JobState.DONE else None
    elif job.state == JobState.RUNNING and rate and rate > 0:
        eta = remaining / rate
        # No task finished for much longer than the rate predicts (a dead worker's task waits for the reaper):
        # the ETA is unknown, not the few seconds the old rate would promise.
        if rates is not None and rates.idle_s(job.id) > max(STALL_MIN_S, STALL_INTERVALS / rate):
            eta = None
    progress = Progress(
        total=total,
        by_state=totals,
        finished=finished,
        fraction=round(fraction, 6),
        throughput_per_s=None if rate is None else round(rate, 4),
        labels_per_s=None if label_rate is None else round(label_rate, 4),
        eta_s=None if eta is None else round(eta, 1),
    )
    return progress, cues
