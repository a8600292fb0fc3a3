"""The dashboard: static HTML/JS/CSS served at /ui (no build step); it talks to the JSON and SSE routes.

The page and its assets need no token (the login form asks for one and keeps it in sessionStorage);
every data request the page makes carries it.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).resolve().parent / "static"


def mount_dashboard(app: FastAPI) -> None:
    """Serve the dashboard's files at /ui (index.html at /ui/)."""
    app.mount("/ui", StaticFiles(directory=STATIC_DIR, html=True), name="ui")
