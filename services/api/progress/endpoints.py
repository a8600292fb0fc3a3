"""SSE routes: live progress of one job (/jobs/{id}/events) or of all the caller's jobs (/events).

Both accept the token as `Authorization: Bearer` or, for browsers' EventSource, as `?token=`.
Events: `job` (JSON like JobEvent) when a job's counters or state change, `deleted` ({"id"}) when it is gone;
comment lines are heartbeats. A job's own stream ends with an `end` event ({"id", "state"}) and closes once
the job reaches a final state (done, failed, cancelled); /events stays open. A tenant holds at most
OMNIDATA_SSE_MAX_PER_TENANT streams at once (429 beyond).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from services.api.deps import SSETenantDep
from services.api.jobs.service import get_job
from services.api.progress.limits import StreamLimits
from services.api.progress.service import Snapshot, event_stream
from services.api.progress.shared import SharedPolls
from services.core.domain.json_types import JSONObject

router = APIRouter(tags=["progress"])

_SSE_HEADERS = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no", "Connection": "keep-alive"}
_SSE_RESPONSES: dict[int | str, JSONObject] = {
    200: {"content": {"text/event-stream": {}}, "description": "a stream of `job` and `deleted` events"}
}


def _stream(request: Request, tenant: str, job_id: int | None) -> StreamingResponse:
    app = request.app
    limits: StreamLimits = app.state.sse_limits
    limits.acquire(tenant)  # TooManyStreams: 429

    def poll(snap: Snapshot) -> tuple[list[JSONObject], list[int]]:
        shared: SharedPolls = app.state.sse_polls
        return shared.poll(tenant, job_id, snap, app.state.rates)

    settings = app.state.settings
    gen = event_stream(
        request,
        poll,
        poll_s=settings.sse_poll_s,
        heartbeat_s=settings.sse_heartbeat_s,
        stop_when_gone=job_id is not None,
        stop_when_final=job_id is not None,
        limiter=limits.limiter,
    )

    async def counted() -> AsyncIterator[str]:
        try:
            async for chunk in gen:
                yield chunk
        finally:
            limits.release(tenant)

    return StreamingResponse(counted(), media_type="text/event-stream", headers=_SSE_HEADERS)


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses=_SSE_RESPONSES,
    summary="Live progress of a job (server-sent events)",
)
async def job_events(
    job_id: Annotated[int, Path(ge=1, le=2**63 - 1)], request: Request, tenant: SSETenantDep
) -> StreamingResponse:
    """Sends the job at once, then again whenever its counters or state change; closes after a final state."""

    def check() -> None:
        with request.app.state.read_sessionmaker() as session:
            get_job(session, owner=tenant, job_id=job_id)  # 404 before the stream starts

    await run_in_threadpool(check)
    return _stream(request, tenant, job_id)


@router.get(
    "/events",
    response_class=StreamingResponse,
    responses=_SSE_RESPONSES,
    summary="Live progress of all your jobs (server-sent events)",
)
async def all_events(request: Request, tenant: SSETenantDep) -> StreamingResponse:
    """Sends each of your recent jobs at once, then every job whose counters or state change."""
    return _stream(request, tenant, None)
