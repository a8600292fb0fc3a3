"""Job routes: create, list (filter by state, paginated), get with progress, lifecycle actions, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from services.api.deps import ReadSessionDep, SessionDep, SettingsDep, StoreDep, TenantDep
from services.api.jobs import service
from services.api.jobs.schemas import JobCreate, JobDetail, JobRead
from services.api.pagination import Page, PageDep
from services.core.db.models import JobState

router = APIRouter(prefix="/jobs", tags=["jobs"])

JobId = Annotated[int, Path(ge=1, le=2**63 - 1, description="job id")]


def _rates(request: Request) -> service.RateTracker:
    rates: service.RateTracker = request.app.state.rates
    return rates


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=JobDetail,
    summary="Create a job",
    responses={404: {"description": "a space is not yours"}, 422: {"description": "invalid spec or cue"}},
)
def create_job(
    body: JobCreate, request: Request, response: Response, session: SessionDep, tenant: TenantDep,
    settings: SettingsDep,
) -> JobDetail:
    """Create a generation job over your spaces; the scheduler plans and runs it."""
    job = service.create_job(
        session, owner=tenant, body=body, plan_memory_mb=settings.plan_memory_mb,
        plan_timeout_s=settings.plan_timeout_s, plan_chunk_views=settings.plan_chunk_views,
    )
    response.headers["Location"] = f"/jobs/{job.id}"
    return service.job_detail(session, job, _rates(request))


@router.get("", response_model=Page[JobRead], summary="List jobs")
def list_jobs(
    request: Request,
    session: ReadSessionDep,
    tenant: TenantDep,
    page: PageDep,
    state: Annotated[
        list[JobState] | None, Query(description="only jobs in these states (repeatable)")
    ] = None,
) -> Page[JobRead]:
    """Your jobs, newest first, with progress."""
    items, total = service.list_jobs(session, owner=tenant, states=state, page=page, rates=_rates(request))
    return Page[JobRead](items=items, total=total, limit=page.limit, offset=page.offset)


@router.get("/{job_id}", response_model=JobDetail, summary="Get a job and its progress")
async def get_job(job_id: JobId, request: Request, tenant: TenantDep) -> Response:
    """A job with task counts per cue and state (from the incremental counters), throughput and ETA."""

    # The hot path of progress polling (dashboards, `omnidata submit`): one thread-pool hop for session +
    # query + serialisation instead of three (session dependency enter/exit, endpoint), and the model is
    # serialised once here instead of being re-validated by FastAPI.
    def work() -> str:
        with request.app.state.read_sessionmaker() as session:
            detail = service.fetch_job_detail(session, owner=tenant, job_id=job_id, rates=_rates(request))
            return detail.model_dump_json()

    return Response(await run_in_threadpool(work), media_type="application/json")


def _action(name: str, doc: str):  # type: ignore[no-untyped-def]
    def endpoint(job_id: JobId, request: Request, session: SessionDep, tenant: TenantDep) -> JobDetail:
        job = service.apply_action(session, owner=tenant, job_id=job_id, action=name)
        return service.job_detail(session, job, _rates(request))

    endpoint.__doc__ = doc
    endpoint.__name__ = f"{name}_job"
    router.add_api_route(
        f"/{{job_id}}/{name}",
        endpoint,
        methods=["POST"],
        response_model=JobDetail,
        summary=doc.split(":")[0],
        responses={409: {"description": "the job's state does not allow this"}},
    )


_action("cancel", "Cancel a job: pending and queued tasks are cancelled at once")
_action("pause", "Pause a running job: nothing more is dispatched until it is resumed")
_action("resume", "Resume a paused job")
_action("retry", "Retry failed tasks: they go back to pending with their attempts reset")


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, summary="Delete a job and its outputs")
def delete_job(job_id: JobId, session: SessionDep, store: StoreDep, tenant: TenantDep) -> Response:
    """Delete a job, its plan, tasks and every output object (an unfinished job is cancelled first)."""
    service.delete_job(session, store, owner=tenant, job_id=job_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
