"""A failed planning attempt: permanent errors fail the job, others leave it claimed for a retry.

Both the scheduler's inline planning and its planner processes record failures here.
"""

from __future__ import annotations

import logging
import traceback
from datetime import timedelta

from sqlalchemy.orm import Session, sessionmaker

from services.core.db.models import Job, JobState, utcnow
from services.core.db.states import set_job_state
from services.core.domain.plan import PlanError
from services.core.ingest.errors import SpaceError
from services.core.storage import ObjectNotFoundError
from services.scheduler.persist import clear_plan

log = logging.getLogger(__name__)

PLAN_RETRY_S = 30  # a planning attempt that failed for a transient reason is retried after this
MAX_PLAN_ATTEMPTS = 3


class PlanningError(Exception):
    """A job that cannot be planned (bad source, impossible spec, a space with no views): it fails."""


def _permanent(exc: BaseException) -> bool:
    """Errors that re-planning cannot fix (the job fails), as opposed to connection trouble (retried)."""
    permanent = PlanningError | PlanError | SpaceError | ObjectNotFoundError | ValueError | KeyError
    return isinstance(exc, permanent)


def record_planning_failure(
    sm: sessionmaker[Session], job_id: int, scheduler_id: str, exc: BaseException,
) -> None:
    """Count a failed planning attempt of a job this scheduler holds: fail it (permanent error, or out of
    attempts) or leave it claimed for a retry after PLAN_RETRY_S."""
    permanent = _permanent(exc)
    log.log(
        logging.WARNING if permanent else logging.ERROR, "planning job %d failed: %s", job_id, exc,
        exc_info=not permanent,
    )
    with sm() as s:
        job = s.get(Job, job_id)
        if job is None or job.state != JobState.PLANNING or job.planner != scheduler_id:
            return
        summary = dict(job.plan_summary or {})
        attempts = int(summary.get("attempts", 0)) + 1
        summary["attempts"] = attempts
        job.plan_summary = summary
        if permanent or attempts >= MAX_PLAN_ATTEMPTS:
            clear_plan(s, job_id)  # the chunks written before the failure
            tail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            error = str(exc) if isinstance(exc, PlanningError) else f"planning failed: {tail}"
            set_job_state(job, JobState.FAILED, finished_at=utcnow(), error=error)
        else:  # leave it claimed; any scheduler may take it again once the lease runs out
            job.planner_lease_until = utcnow() + timedelta(seconds=PLAN_RETRY_S)
        s.commit()
