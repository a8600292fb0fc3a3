"""Keep `?token=` out of every log: an ASGI middleware takes it off the query string before anything runs.

Access logs (uvicorn's included) print the query string, and so would any handler that logs the URL. The
middleware removes every `token` parameter from `scope["query_string"]` in place (the server logs from the
same scope) and keeps the first value in the scope under QUERY_TOKEN_KEY, where the SSE routes' dependency
(`deps.get_tenant_sse`) reads it; other routes ignore it and need a bearer header.
"""

from __future__ import annotations

from urllib.parse import parse_qsl, urlencode

from starlette.types import ASGIApp, Receive, Scope, Send

QUERY_TOKEN_KEY = "omnidata.query_token"
_PARAM = "token"


class QueryTokenScrubber:
    """Pure ASGI middleware (no body buffering, SSE streams pass through untouched)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        # Parsed whenever there is a query string: a cheap substring test would miss `%74oken=`.
        if scope["type"] == "http" and scope.get("query_string"):
            pairs = parse_qsl(scope["query_string"].decode("latin-1"), keep_blank_values=True)
            tokens = [v for k, v in pairs if k == _PARAM]
            if tokens:
                scope[QUERY_TOKEN_KEY] = tokens[0]
                kept = [(k, v) for k, v in pairs if k != _PARAM]
                scope["query_string"] = urlencode(kept).encode("latin-1")
        await self.app(scope, receive, send)
