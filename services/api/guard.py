"""Request guard (ASGI middleware): a request body is read only from a caller with a valid token, and only
up to a size limit.

FastAPI reads and parses a JSON body before the route's dependencies (the token check) run, and without a
bound: a 50 MB body from anyone would hold the event loop (and /health) while it is parsed. This guard runs
first, on the headers alone: a request that carries a body gets 401 without a valid bearer token and 413 when
it declares more than `Settings.request_max_bytes`; a body sent without a length (chunked) is counted while
it is buffered and refused at the same limit. Multipart uploads stream to disk under their own, larger limit
(services/api/spaces/upload.py), so only their token is checked here. Requests without a body (GET, /health,
the dashboard) pass untouched; their routes check the token as before.
"""

from __future__ import annotations

from fastapi import HTTPException, status
from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.api.deps import tenant_for
from services.core.settings import Settings


def _has_body(headers: Headers) -> bool:
    length = headers.get("content-length")
    if length is not None:
        return length.strip() not in ("", "0")
    return "chunked" in headers.get("transfer-encoding", "").lower()


def _bearer(headers: Headers) -> str | None:
    scheme, _, token = headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer":
        return None
    return token.strip() or None


def _too_large(limit: int) -> JSONResponse:
    return JSONResponse(
        {"detail": f"request body exceeds the limit of {limit} bytes (OMNIDATA_REQUEST_MAX_BYTES); "
                   "upload scans as multipart/form-data to POST /spaces"},
        status_code=status.HTTP_413_CONTENT_TOO_LARGE,
    )


class RequestGuard:
    """Checks the token and the size of a request body before any of it is read (see the module docstring)."""

    def __init__(self, app: ASGIApp, *, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        if not _has_body(headers):
            await self.app(scope, receive, send)
            return
        try:
            tenant_for(self.settings, _bearer(headers))
        except HTTPException as e:
            await JSONResponse({"detail": e.detail}, status_code=e.status_code, headers=e.headers)(
                scope, receive, send
            )
            return
        if headers.get("content-type", "").lower().startswith("multipart/form-data"):
            await self.app(scope, receive, send)  # streamed to disk under upload_max_bytes
            return
        limit = self.settings.request_max_bytes
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limit:
            await _too_large(limit)(scope, receive, send)
            return
        body = await _read_bounded(receive, limit)
        if body is None:
            await _too_large(limit)(scope, receive, send)
            return
        await self.app(scope, _replay(body, receive), send)


async def _read_bounded(receive: Receive, limit: int) -> bytes | None:
    """The whole body, or None as soon as it grows past `limit` bytes (the rest is never read)."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":  # the client went away
            return b"".join(chunks)
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            return None
        chunks.append(chunk)
        if not message.get("more_body", False):
            return b"".join(chunks)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A receive callable that gives `body` once, then whatever the connection sends (a disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay
