"""Exception handlers: every error is JSON `{"detail": "<clear message>"}`; client mistakes are never a 500.

The services raise domain errors (services.core.domain.errors); `_domain_error` is the one place that turns
them into HTTP statuses.

Validation errors keep pydantic's field locations in `errors` ([{loc, msg, type}]) and summarise them in
`detail` ("body.spec.views.resolution: Input should be less than or equal to 4096").
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import TypedDict

from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic_core import ErrorDetails
from sqlalchemy.exc import DataError, IntegrityError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from services.api.designer.pool import DesignFailed
from services.core.domain.errors import (
    Conflict,
    DomainError,
    Forbidden,
    Invalid,
    NotFound,
    TooLarge,
    TooManyRequests,
)
from services.core.storage import StorageError

log = logging.getLogger("omnidata.api")

MAX_ERRORS = 20  # a 10,000-item list of bad values gets 20 errors listed back, not 10,000
MAX_ERROR_TEXT = 300  # characters of a message or location part: messages may quote the input


def clip(text: str, limit: int = MAX_ERROR_TEXT) -> str:
    """`text` cut to `limit` characters, saying how much was left out (error responses never echo huge
    inputs)."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text) - limit} more characters)"


def _loc(loc: Iterable[str | int]) -> list[str | int]:
    # a location names the input's own keys (an unknown field), so it is clipped like a message
    return [p if isinstance(p, int) else clip(str(p), 100) for p in loc]


class FieldError(TypedDict):
    """One failing field of a 422: where (path of keys and indexes), why, and pydantic's error type."""

    loc: list[str | int]
    msg: str
    type: str


def validation_errors(errors: Iterable[ErrorDetails]) -> list[FieldError]:
    """Pydantic errors reduced to JSON-safe {loc, msg, type}: inputs are not echoed, messages are clipped."""
    return [
        {"loc": _loc(e.get("loc", ())), "msg": clip(str(e.get("msg", ""))), "type": str(e.get("type", ""))}
        for e in list(errors)[:MAX_ERRORS]
    ]


def summarize(errors: list[FieldError], total: int | None = None) -> str:
    """One line naming each failing field: `loc.path: message; ...` (`total`: errors before clipping)."""
    total = len(errors) if total is None else total
    parts = []
    for e in errors[:10]:
        where = ".".join(str(p) for p in e["loc"])
        parts.append(f"{where}: {e['msg']}" if where else e["msg"])
    if total > 10:
        parts.append(f"... and {total - 10} more")
    return "; ".join(parts) or "invalid request"


def error_response(status_code: int, detail: str, **extra: object) -> JSONResponse:
    """A JSON error response with `detail` and optional extra fields."""
    return JSONResponse({"detail": detail, **extra}, status_code=status_code)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    detail = clip(exc.detail if isinstance(exc.detail, str) else str(exc.detail), 2000)
    return JSONResponse(
        {"detail": detail}, status_code=exc.status_code, headers=getattr(exc, "headers", None)
    )


# most specific first: a domain error class is matched by isinstance in this order
DOMAIN_STATUS: tuple[tuple[type[DomainError], int], ...] = (
    (NotFound, status.HTTP_404_NOT_FOUND),
    (Conflict, status.HTTP_409_CONFLICT),
    (Forbidden, status.HTTP_403_FORBIDDEN),
    (TooLarge, status.HTTP_413_CONTENT_TOO_LARGE),
    (TooManyRequests, status.HTTP_429_TOO_MANY_REQUESTS),
    (Invalid, status.HTTP_422_UNPROCESSABLE_CONTENT),
)


def domain_status(exc: DomainError) -> int:
    """The HTTP status of a domain error (422 for one of no listed kind: the request cannot be done as
    asked)."""
    return next(
        (code for cls, code in DOMAIN_STATUS if isinstance(exc, cls)), status.HTTP_422_UNPROCESSABLE_CONTENT
    )


async def _domain_error(request: Request, exc: DomainError) -> JSONResponse:
    response = error_response(domain_status(exc), clip(str(exc), 2000))
    if isinstance(exc, TooManyRequests):  # when to try again, in whole seconds (RFC 9110)
        response.headers["Retry-After"] = str(exc.retry_after_s)
    return response


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    raw = exc.errors()
    errors = validation_errors(raw)  # at most MAX_ERRORS; `detail` still says how many there were
    return error_response(status.HTTP_422_UNPROCESSABLE_CONTENT, summarize(errors, len(raw)), errors=errors)


async def _data_error(request: Request, exc: DataError) -> JSONResponse:
    # The database refused a value the request carried (out of range, bad encoding): the client's mistake.
    msg = str(getattr(exc, "orig", exc)).splitlines()[0]
    return error_response(status.HTTP_422_UNPROCESSABLE_CONTENT, f"invalid value: {msg}")


async def _integrity_error(request: Request, exc: IntegrityError) -> JSONResponse:
    msg = str(getattr(exc, "orig", exc)).splitlines()[0]
    return error_response(status.HTTP_409_CONFLICT, f"conflict with existing data: {msg}")


async def _operational_error(request: Request, exc: OperationalError) -> JSONResponse:
    log.warning("database unavailable: %s", exc)
    return error_response(status.HTTP_503_SERVICE_UNAVAILABLE, "database unavailable, try again shortly")


async def _pool_timeout(request: Request, exc: PoolTimeout) -> JSONResponse:
    # Every database connection stayed busy for the pool's whole timeout: an overloaded service, not a bug.
    log.warning("no database connection free on %s %s: %s", request.method, request.url.path, exc)
    response = error_response(status.HTTP_503_SERVICE_UNAVAILABLE, "the service is busy, try again shortly")
    response.headers["Retry-After"] = "5"
    return response


async def _storage_error(request: Request, exc: StorageError) -> JSONResponse:
    # The object store is missing or refuses writes: the operator's problem, named, never a bare 500.
    log.error("object storage failed on %s %s: %s", request.method, request.url.path, exc)
    return error_response(status.HTTP_503_SERVICE_UNAVAILABLE, f"object storage unavailable: {exc}")


async def _design_failed(request: Request, exc: DesignFailed) -> JSONResponse:
    # The designer's process crashed (not the spec): the next call starts a fresh one.
    log.error("designer failed on %s %s: %s", request.method, request.url.path, exc)
    response = error_response(status.HTTP_503_SERVICE_UNAVAILABLE, f"{exc}; try again")
    response.headers["Retry-After"] = "1"
    return response


async def _unhandled(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return error_response(status.HTTP_500_INTERNAL_SERVER_ERROR, "internal server error")


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers above on `app`."""
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    app.add_exception_handler(DomainError, _domain_error)  # type: ignore[arg-type]
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(DataError, _data_error)  # type: ignore[arg-type]
    app.add_exception_handler(IntegrityError, _integrity_error)  # type: ignore[arg-type]
    app.add_exception_handler(OperationalError, _operational_error)  # type: ignore[arg-type]
    app.add_exception_handler(PoolTimeout, _pool_timeout)  # type: ignore[arg-type]
    app.add_exception_handler(StorageError, _storage_error)  # type: ignore[arg-type]
    app.add_exception_handler(DesignFailed, _design_failed)  # type: ignore[arg-type]
    app.add_exception_handler(Exception, _unhandled)
