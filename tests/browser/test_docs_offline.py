"""/docs in headless Chromium with every request off this server refused: Swagger UI renders the service's
operations from installed files, and the page's CSP (no inline script) reports no violation."""

from __future__ import annotations

from typing import Any

import pytest

from services.core.storage import LocalStore
from tests.fixtures.api import live_server, make_api

pytestmark = pytest.mark.slow


def test_docs_render_offline_under_the_csp(pg_url: str, local_store: LocalStore, browser: Any) -> None:
    with make_api(pg_url, local_store) as api, live_server(api.app) as base:
        ctx = browser.new_context()
        outside: list[str] = []

        def only_here(route: Any) -> None:
            if route.request.url.startswith(base):
                route.continue_()
            else:  # the network a machine without internet access has
                outside.append(route.request.url)
                route.abort()

        ctx.route("**/*", only_here)
        try:
            page = ctx.new_page()
            errors: list[str] = []
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"{base}/docs")
            page.wait_for_selector(".opblock-summary-path[data-path=\"/spaces/register\"]", timeout=30_000)
            assert page.locator(".opblock").count() > 20  # the operations, rendered
            assert outside == [] and errors == [], (outside, errors)
        finally:
            ctx.close()
