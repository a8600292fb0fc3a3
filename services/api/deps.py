"""Request dependencies (database session, object store, settings and the caller's tenant), injected so
routes stay thin and tests can swap them.

Routes take the `Annotated` aliases below. The cheap ones are `async def` so FastAPI runs them on the event
loop instead of handing each to the thread pool. Authentication is a bearer token (`Authorization: Bearer
<token>`) whose sha256 maps to a tenant in `Settings.api_tokens`; the SSE routes also accept `?token=` because
a browser's EventSource cannot set headers.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from services.api.query_token import QUERY_TOKEN_KEY
from services.core.settings import Settings
from services.core.storage.base import ObjectStore

bearer_scheme = HTTPBearer(auto_error=False, description="API token: `Authorization: Bearer <token>`")
_UNAUTHORIZED_HEADERS = {"WWW-Authenticate": "Bearer"}


async def get_settings(request: Request) -> Settings:
    """The app's settings (set once by create_app)."""
    settings: Settings = request.app.state.settings
    return settings


def get_session(request: Request) -> Iterator[Session]:
    """A database session for one request; closed (rolled back if uncommitted) afterwards."""
    with request.app.state.sessionmaker() as session:
        yield session


def get_read_session(request: Request) -> Iterator[Session]:
    """A session for reads only: autocommit on Postgres, so no BEGIN/ROLLBACK round trips per request."""
    with request.app.state.read_sessionmaker() as session:
        yield session


async def get_store(request: Request) -> ObjectStore:
    """The object store holding space sources and job outputs."""
    store: ObjectStore = request.app.state.store
    return store


def tenant_for(settings: Settings, token: str | None) -> str:
    """The tenant whose token this is (401 without one or with an unknown one); the body guard checks it
    too."""
    if not token:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing API token: send 'Authorization: Bearer <token>'",
            headers=_UNAUTHORIZED_HEADERS,
        )
    tenant = settings.tenant_for_token(token)
    if tenant is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "invalid API token", headers=_UNAUTHORIZED_HEADERS)
    return tenant


async def get_tenant(
    request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]
) -> str:
    """The tenant of the bearer token; 401 when it is missing or unknown."""
    return tenant_for(request.app.state.settings, creds.credentials if creds else None)


async def get_tenant_sse(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
    token: Annotated[
        str | None,
        Query(description="API token, for EventSource clients that cannot send headers"),
    ] = None,
) -> str:
    """Like get_tenant, but a `?token=` query parameter is accepted too (SSE routes only).

    The `token` parameter is declared for the API docs; its value arrives through the scope, because
    QueryTokenScrubber has already taken it off the query string so that no log ever shows it.
    """
    query_token = request.scope.get(QUERY_TOKEN_KEY, token)
    return tenant_for(request.app.state.settings, creds.credentials if creds else query_token)


SettingsDep = Annotated[Settings, Depends(get_settings)]
# Sessions close when the route returns, before its response is sent: a client that reads slowly (a big page,
# a stream) never holds a database connection ("request" scope would keep it until the last byte).
SessionDep = Annotated[Session, Depends(get_session, scope="function")]
ReadSessionDep = Annotated[Session, Depends(get_read_session, scope="function")]
StoreDep = Annotated[ObjectStore, Depends(get_store)]
TenantDep = Annotated[str, Depends(get_tenant)]
SSETenantDep = Annotated[str, Depends(get_tenant_sse)]
