"""The interactive API docs at /docs, served offline: Swagger UI's files come from the `swagger-ui-bundle-v2`
package (installed from PyPI with the service), the page and its start-up script from here.

FastAPI's own /docs page loads Swagger UI from a CDN and starts it with an inline script: it shows nothing
on a machine without internet access, and the CSP the dashboard's pages get refuses inline scripts. So
FastAPI's docs routes are turned off (`docs_url=None`) and this module serves the same UI from local files.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from swagger_ui_bundle import swagger_ui_path

HERE = Path(__file__).resolve().parent
PAGE = """<!doctype html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <title>{title} - API docs</title>
  <link rel="stylesheet" href="/docs/swagger-ui/swagger-ui.css">
  <link rel="icon" href="data:,">
</head>
<body>
  <div id="swagger-ui" data-openapi-url="{openapi_url}"></div>
  <script src="/docs/swagger-ui/swagger-ui-bundle.js"></script>
  <script src="/docs/static/start.js"></script>
</body>
</html>
"""


def mount_docs(app: FastAPI) -> None:
    """Serve Swagger UI at /docs from installed files (no CDN, no inline script)."""
    app.mount("/docs/swagger-ui", StaticFiles(directory=swagger_ui_path), name="swagger-ui")
    app.mount("/docs/static", StaticFiles(directory=HERE / "static"), name="docs-static")
    page = PAGE.format(title=app.title, openapi_url=app.openapi_url or "/openapi.json")

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return HTMLResponse(page)
