"""Worker routes: the render workers with heartbeat age, current task and labels/s."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials

from services.api.deps import ReadSessionDep, SettingsDep, bearer_scheme, get_tenant
from services.api.pagination import Page, PageDep
from services.api.workers import service
from services.api.workers.schemas import WorkerRead

router = APIRouter(prefix="/workers", tags=["workers"])


@router.get("", response_model=Page[WorkerRead], summary="List workers")
async def list_workers(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
    session: ReadSessionDep,
    page: PageDep,
    settings: SettingsDep,
    alive: Annotated[bool | None, Query(description="only live (true) or stale (false) workers")] = None,
) -> Page[WorkerRead]:
    """Workers by most recent heartbeat; a current task is detailed only when it is one of yours.

    `tasks_done`, `labels_per_s` and `labels` sum every tenant's work: an operator token
    (OMNIDATA_OPERATOR_TOKENS) sees them, a tenant's token gets null and {}.
    """
    operator = creds is not None and settings.is_operator_token(creds.credentials)
    tenant = None if operator else await get_tenant(request, creds)
    items, total = await run_in_threadpool(
        service.list_workers, session, tenant=tenant, page=page, stale_s=settings.heartbeat_timeout_s,
        alive=alive,
    )
    return Page[WorkerRead](items=items, total=total, limit=page.limit, offset=page.offset)
