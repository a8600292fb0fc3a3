"""Plan and task routes of a job: views (with task states, optional output links), tasks, plan, throughput."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query, Request, Response

from services.api.deps import ReadSessionDep, SettingsDep, StoreDep, TenantDep
from services.api.jobs.service import get_job
from services.api.outputs.service import link_base, links
from services.api.pagination import Page, PageDep, page_response
from services.api.spaces.service import not_found
from services.api.throttle import BulkSlot, run_bulk
from services.api.views import service
from services.api.views.compacted import find_compacted_task
from services.api.views.schemas import Plan, TaskRead, Throughput, ViewRead
from services.core.db.compacted import has_compacted
from services.core.db.models import Task, TaskState
from services.core.domain.cues import CATALOG

router = APIRouter(prefix="/jobs/{job_id}", tags=["views"])

JobId = Annotated[int, Path(ge=1, le=2**63 - 1, description="job id")]
CueName = Literal[tuple(CATALOG)]  # type: ignore[valid-type]
SpaceFilter = Annotated[int | None, Query(ge=1, le=2**63 - 1, description="only this space")]
PointFilter = Annotated[int | None, Query(ge=0, le=2**31 - 1, description="only this point")]
StateFilter = Annotated[TaskState | None, Query(description="task state")]
CueFilter = Annotated[CueName | None, Query(description="cue name")]  # type: ignore[valid-type]


@router.get("/views", response_model=Page[ViewRead], summary="Views of a job with their task states",
            dependencies=[BulkSlot])
async def list_views(
    job_id: JobId,
    request: Request,
    session: ReadSessionDep,
    store: StoreDep,
    settings: SettingsDep,
    tenant: TenantDep,
    page: PageDep,
    space_id: SpaceFilter = None,
    point: PointFilter = None,
    state: StateFilter = None,
    cue: CueFilter = None,
    complete: Annotated[bool, Query(description="only views whose every task is done")] = False,
    urls: Annotated[bool, Query(description="include pre-signed links to finished outputs")] = False,
) -> Response:
    """Views in (space, point, view) order; `state`/`cue` keep views having such a task."""

    def work() -> Response:
        job = get_job(session, owner=tenant, job_id=job_id)
        rows, total = service.list_views(session, job=job, page=page, space_id=space_id, point=point,
                                         state=state, cue=cue, complete=complete)
        items = []
        for view, space_name, tasks in rows:
            item = service.view_read(view, space_name, tasks)
            if urls:
                item.outputs = links(store, settings, job=job, space_name=space_name, tasks=tasks,
                                     base_url=link_base(settings), view=view.v)
            items.append(item)
        return page_response(Page[ViewRead](items=items, total=total, limit=page.limit, offset=page.offset))

    return await run_bulk(request, work)


@router.get("/tasks", response_model=Page[TaskRead], summary="Tasks of a job",
            dependencies=[BulkSlot])
async def list_tasks(
    job_id: JobId,
    request: Request,
    session: ReadSessionDep,
    tenant: TenantDep,
    page: PageDep,
    state: StateFilter = None,
    cue: CueFilter = None,
    space_id: SpaceFilter = None,
) -> Response:
    """Tasks by id with their state, attempts, worker, error (when failed), output key and duration; done
    tasks of compacted views (services.scheduler.compaction) follow in view order, without worker or
    queued/started
    times."""

    def work() -> Response:
        job = get_job(session, owner=tenant, job_id=job_id)
        rows, total = service.list_tasks(session, job=job, page=page, state=state, cue=cue, space_id=space_id)
        items = [service.task_read(t) for t in rows]
        return page_response(Page[TaskRead](items=items, total=total, limit=page.limit, offset=page.offset))

    return await run_bulk(request, work)


@router.get("/tasks/{task_id}", response_model=TaskRead, summary="One task of a job")
def get_task(
    job_id: JobId,
    task_id: Annotated[int, Path(ge=1, le=2**63 - 1)],
    session: ReadSessionDep,
    tenant: TenantDep,
) -> TaskRead:
    """A task with its error (when failed)."""
    job = get_job(session, owner=tenant, job_id=job_id)
    task = session.get(Task, task_id)
    if task is None and has_compacted(session, job.id):
        task = find_compacted_task(session, job, task_id)
    if task is None or task.job_id != job.id:
        raise not_found("task", task_id)
    return service.task_read(task)


@router.get("/plan", response_model=Plan, summary="Cameras and points of a job (for a top-down plot)",
            dependencies=[BulkSlot])
async def get_plan(
    job_id: JobId,
    request: Request,
    session: ReadSessionDep,
    tenant: TenantDep,
    space_id: SpaceFilter = None,
    max_items: Annotated[int, Query(ge=1, le=service.MAX_PLAN_ITEMS)] = service.MAX_PLAN_ITEMS,
) -> Response:
    """Per space: bounds, cameras [x, y, z, yaw], points [x, y, z, n_views], views [point, camera]
    (metres)."""

    def work() -> Response:
        job = get_job(session, owner=tenant, job_id=job_id)
        spaces = service.plan(session, job=job, space_id=space_id, max_items=max_items)
        plan = Plan(job_id=job.id, spaces=spaces)
        # serialized here, in the bulk thread: FastAPI would do it on the event loop
        return Response(plan.model_dump_json(), media_type="application/json")

    return await run_bulk(request, work)


@router.get("/throughput", response_model=Throughput, summary="Finished tasks over time")
def get_throughput(
    job_id: JobId,
    session: ReadSessionDep,
    tenant: TenantDep,
    buckets: Annotated[int, Query(ge=1, le=1000, description="number of time buckets")] = 60,
) -> Throughput:
    """Done tasks per time bucket (from task finished_at) since the job started."""
    job = get_job(session, owner=tenant, job_id=job_id)
    bucket_s, series = service.throughput(session, job=job, buckets=buckets)
    return Throughput(job_id=job.id, bucket_s=bucket_s, buckets=series)
