"""Response headers that keep the dashboard from being framed, sniffed or made to run injected script.

Every response says `X-Content-Type-Options: nosniff` (a signed link's PNG is never taken for HTML). The
dashboard (/ui) and the API docs (/docs, /redoc) also get a Content-Security-Policy that allows scripts,
styles and connections from this origin only (no inline script, no eval, no CDN), refuses to be framed
(`frame-ancestors 'none'`, and `X-Frame-Options: DENY` for older browsers), and sends no referrer that
could carry a signed link elsewhere. Images may also come from the configured public base URL (signed
preview links) and, on S3, from the bucket's endpoint (pre-signed output links).
"""

from __future__ import annotations

from urllib.parse import urlsplit

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.settings import Settings

PAGE_PREFIXES = ("/ui", "/docs", "/redoc")


def _origin(url: str | None) -> str | None:
    if not url:
        return None
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}" if parts.scheme and parts.netloc else None


def content_security_policy(settings: Settings) -> str:
    """The dashboard's CSP: this origin only, plus the image origins of signed and pre-signed links."""
    images = " ".join(o for o in {_origin(settings.public_base_url), _origin(settings.s3_endpoint_url)} if o)
    return "; ".join([
        "default-src 'self'",
        "script-src 'self'",
        "style-src 'self'",
        f"img-src 'self' data: blob: {images}".rstrip(),
        "connect-src 'self'",
        "object-src 'none'",
        "base-uri 'self'",
        "form-action 'self'",
        "frame-ancestors 'none'",
    ])


class SecurityHeaders:
    """ASGI middleware adding the headers above (pure ASGI: streaming responses pass through untouched)."""

    def __init__(self, app: ASGIApp, *, settings: Settings):
        self.app = app
        self.csp = content_security_policy(settings).encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        page = str(scope.get("path", "")).startswith(PAGE_PREFIXES)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                headers.append((b"x-content-type-options", b"nosniff"))
                if page:
                    headers += [(b"content-security-policy", self.csp), (b"x-frame-options", b"DENY"),
                                (b"referrer-policy", b"no-referrer")]
                message["headers"] = headers
            await send(message)

        await self.app(scope, receive, send_with_headers)
