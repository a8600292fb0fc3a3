"""Designer routes: a spec's plan (drawings and distributions) and a few small previews, before any job
exists.

Each call plans in one of the API's warm designer processes (services.api.designer.pool) within a time budget,
never in the API process; a tenant has at most OMNIDATA_TENANT_DESIGN_CONCURRENCY of them under way (429 past
it)."""

from __future__ import annotations

from typing import Any

import anyio
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool

from services.api.deps import ReadSessionDep, SettingsDep, StoreDep, TenantDep
from services.api.designer import service
from services.api.designer.pool import DesignPool
from services.api.designer.schemas import DesignFit, DesignPlan, DesignPreviews, DesignRequest
from services.api.throttle import DesignSlot
from services.core.domain.jobspec import JobSpec

router = APIRouter(prefix="/designer", tags=["designer"])

_REFUSALS: dict[int | str, dict[str, Any]] = {
    404: {"description": "a space that is not yours"},
    422: {
        "description": "a bad spec (each failing field named), or one the spaces cannot meet in the budget"
    },
    429: {"description": "too many designer calls of this tenant under way"},
}


def _pool(request: Request) -> DesignPool:
    pool: DesignPool = request.app.state.designer
    return pool


@router.get("/schema", summary="The JobSpec's JSON schema (the designer's form)")
def schema(request: Request, tenant: TenantDep) -> dict[str, Any]:
    """JobSpec's JSON schema; starts a warm designer process in the background, so the first plan is quick."""
    _pool(request).warm()
    return JobSpec.model_json_schema()


async def _prepared(
    body: DesignRequest, session: Any, store: Any, settings: Any, tenant: str
) -> tuple[JobSpec, list[dict[str, Any]]]:
    spec = service.spec_of(body)
    spaces = await run_in_threadpool(
        service.sources, session, store, settings, owner=tenant, space_ids=body.space_ids, spec=spec
    )
    return spec, spaces


@router.post(
    "/plan",
    response_model=DesignPlan,
    summary="Plan a spec over spaces: drawings and distributions",
    responses=_REFUSALS,
    dependencies=[DesignSlot],
)
async def design_plan(
    body: DesignRequest,
    request: Request,
    session: ReadSessionDep,
    store: StoreDep,
    settings: SettingsDep,
    tenant: TenantDep,
) -> DesignPlan:
    """The spec (JSON and YAML), a sample of its cameras, points and views per space, and histograms of its
    views' field of view, pitch, roll, height, distance, obliqueness and views per point (fixed bin edges)."""
    spec, spaces = await _prepared(body, session, store, settings, tenant)
    return await anyio.to_thread.run_sync(service.plan, _pool(request), spec, spaces, tenant)


@router.post(
    "/previews",
    response_model=DesignPreviews,
    summary="Small previews of a few planned views",
    responses=_REFUSALS,
    dependencies=[DesignSlot],
)
async def design_previews(
    body: DesignRequest,
    request: Request,
    session: ReadSessionDep,
    store: StoreDep,
    settings: SettingsDep,
    tenant: TenantDep,
) -> DesignPreviews:
    """rgb, depth, normal and segment previews (96 px PNG data URLs) of `previews` views spread over
    the plan."""
    spec, spaces = await _prepared(body, session, store, settings, tenant)
    return await anyio.to_thread.run_sync(
        service.previews, _pool(request), spec, spaces, body.previews, tenant
    )


@router.post(
    "/fit",
    response_model=DesignFit,
    summary="Fit a spec to a space's posed capture",
    responses=_REFUSALS,
    dependencies=[DesignSlot],
)
async def design_fit(
    body: DesignRequest,
    request: Request,
    session: ReadSessionDep,
    store: StoreDep,
    settings: SettingsDep,
    tenant: TenantDep,
) -> DesignFit:
    """The spec with its fov, pitch, height and roll knobs fitted to the capture uploaded with the first space
    (re-planned a few rounds), how close each came (KS statistic), and the capture's histograms."""
    spec, spaces = await _prepared(body, session, store, settings, tenant)
    return await anyio.to_thread.run_sync(service.fit, _pool(request), spec, spaces, tenant)
