"""Worker routes: the render workers with heartbeat age, current task and labels/s."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from services.api.deps import ReadSessionDep, SettingsDep, TenantDep
from services.api.pagination import Page, PageDep
from services.api.workers import service
from services.api.workers.schemas import WorkerRead

router = APIRouter(prefix="/workers", tags=["workers"])


@router.get("", response_model=Page[WorkerRead], summary="List workers")
def list_workers(
    session: ReadSessionDep,
    tenant: TenantDep,
    page: PageDep,
    settings: SettingsDep,
    alive: Annotated[bool | None, Query(description="only live (true) or stale (false) workers")] = None,
) -> Page[WorkerRead]:
    """Workers by most recent heartbeat; a current task is detailed only when it is one of yours."""
    items, total = service.list_workers(
        session, tenant=tenant, page=page, stale_s=settings.heartbeat_timeout_s, alive=alive
    )
    return Page[WorkerRead](items=items, total=total, limit=page.limit, offset=page.offset)
