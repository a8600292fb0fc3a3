"""Operations routes: /health (liveness, no auth), /ready (dependencies), /metrics (Prometheus text)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials
from pydantic import BaseModel

from services.api.deps import bearer_scheme, get_tenant
from services.api.ops import service

router = APIRouter(tags=["ops"])


class Health(BaseModel):
    """The process is up."""

    status: str
    version: str


@router.get("/health", response_model=Health, summary="Liveness (no token needed)")
async def health(request: Request) -> Health:
    """200 while the process serves requests; checks nothing else. Runs on the event loop, never in the
    request thread pool, so a pool busy with uploads or queries does not delay it."""
    return Health(status="ok", version=request.app.version)


@router.get(
    "/ready",
    summary="Readiness: database reachable and migrated, broker reachable, storage writable",
    responses={503: {"description": "a dependency failed; `failed` names it"}},
)
async def ready(
    request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]
) -> JSONResponse:
    """200 when the database, the broker (Redis PING) and the object store answer; else 503 naming the
    failures.

    Orchestrator probes call this without a token, so it answers without one; error messages (which may
    name hosts) are included only for a caller with a valid token.
    """
    checks = await service.readiness(request.app)
    authed = creds is not None and request.app.state.settings.tenant_for_token(creds.credentials) is not None
    failed = [name for name, c in checks.items() if not c.ok and not c.skipped]
    body = {
        "status": "ready" if not failed else "unavailable",
        "failed": failed,
        "checks": {
            name: {
                "ok": c.ok,
                "latency_ms": c.latency_ms,
                **({"skipped": True} if c.skipped else {}),
                **({"error": c.error} if c.error and authed else {}),
            }
            for name, c in checks.items()
        },
    }
    if failed:
        body["detail"] = "not ready: " + ", ".join(
            f"{n} ({checks[n].error})" if authed else n for n in failed
        )
        return JSONResponse(body, status_code=503)
    return JSONResponse(body)


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    summary="Prometheus metrics",
    responses={200: {"content": {"text/plain": {}}}},
)
async def metrics(
    request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]
) -> PlainTextResponse:
    """Tasks by state, dispatch/completion counts, workers and the task duration histogram.

    An operator token (OMNIDATA_OPERATOR_TOKENS, for Prometheus) sees the whole service and the broker queue
    depths; a tenant's token sees the figures of its own jobs only.
    """
    settings = request.app.state.settings
    operator = creds is not None and settings.is_operator_token(creds.credentials)
    owner = None if operator else await get_tenant(request, creds)
    body = await run_in_threadpool(service.cached_metrics, request.app, owner)
    return PlainTextResponse(body, media_type="text/plain; version=0.0.4; charset=utf-8")
