"""The FastAPI application: `create_app(settings)` wires routes, storage and the database.

Routes live in feature folders (spaces, jobs, views, outputs, workers, progress, ops), each with endpoints.py
(HTTP), schemas.py (API models, separate from ORM rows) and service.py (logic taking keyword arguments).
The dashboard is static HTML/JS/CSS served at /ui. This service imports only services.core (never the
scheduler, the worker or bpy).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from sqlalchemy import Engine

from services.api.dashboard.endpoints import mount_dashboard
from services.api.designer.endpoints import router as designer_router
from services.api.designer.pool import DesignPool
from services.api.docs_page import mount_docs
from services.api.errors import install_error_handlers
from services.api.guard import RequestGuard
from services.api.jobs.endpoints import router as jobs_router
from services.api.jobs.rates import RateTracker
from services.api.limits import LazyLimiter
from services.api.ops.endpoints import router as ops_router
from services.api.outputs.endpoints import router as outputs_router
from services.api.progress.endpoints import router as progress_router
from services.api.progress.limits import StreamLimits
from services.api.progress.shared import SharedPolls
from services.api.query_token import QueryTokenScrubber
from services.api.security_headers import SecurityHeaders
from services.api.spaces.endpoints import router as spaces_router
from services.api.throttle import TenantThrottle, budgets
from services.api.views.endpoints import router as views_router
from services.api.workers.endpoints import router as workers_router
from services.core.db.engine import make_engine, make_sessionmaker, schema_heads
from services.core.settings import Settings, get_settings
from services.core.storage import ObjectStore, open_store
from services.core.temp_dirs import UPLOAD_KINDS, sweep_orphans

log = logging.getLogger("omnidata.api")

API_VERSION = "0.1.0"

OPENAPI_TAGS = [
    {"name": "spaces", "description": "Upload and register scans (meshes, or .zip/.glb with textures)."},
    {
        "name": "jobs",
        "description": "Generation jobs: create, list, progress, cancel/pause/resume/retry, delete.",
    },
    {
        "name": "views",
        "description": "Plans and tasks of a job: cameras, points, views, task states and errors.",
    },
    {
        "name": "outputs",
        "description": "Pre-signed links to a view's cue files; the job's manifest and job.json.",
    },
    {"name": "progress", "description": "Server-sent events with live progress counters."},
    {"name": "workers", "description": "Render workers and their heartbeats."},
    {"name": "designer", "description": "A spec's plan, distributions and previews before a job exists."},
    {"name": "ops", "description": "Health, readiness and Prometheus metrics."},
]


def _set_state(app: FastAPI, settings: Settings, engine: Engine, store: ObjectStore) -> None:
    """What the routes find on `app.state`: settings, sessions, store, rate tracker, caches."""
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessionmaker = make_sessionmaker(engine)
    # Reads (progress polls, lists) need no transaction: autocommit saves the BEGIN and ROLLBACK round trips.
    read_engine = engine if settings.is_sqlite else engine.execution_options(isolation_level="AUTOCOMMIT")
    app.state.read_sessionmaker = make_sessionmaker(read_engine)
    app.state.store = store
    app.state.redis = None  # created on first use by ops.service.redis_client
    app.state.rates = RateTracker()
    app.state.sse_limits = StreamLimits(settings.sse_max_per_tenant, settings.sse_poll_threads)
    app.state.sse_polls = SharedPolls(app.state.read_sessionmaker, max_age_s=settings.sse_poll_s / 2)
    # Each scan read (an upload's check, an up choice, a side view) is a CPU-bound child process: a few at a
    # time, so 50 uploads or 40 up choices do not starve the server; the throttle caps each tenant's share.
    app.state.scan_reads = LazyLimiter(settings.upload_parse_concurrency)
    app.state.throttle = TenantThrottle(budgets(settings))
    app.state.preview_draws = LazyLimiter(settings.preview_concurrency)
    app.state.bulk_reads = LazyLimiter(settings.bulk_read_threads)
    app.state.designer = DesignPool(settings.designer_processes, settings.designer_timeout_s)
    app.state.metrics_cache = {}
    app.state.schema_heads = schema_heads()  # what /ready expects the database's revision to be
    app.state.storage_probe = None  # (time, outcome) of /ready's last storage probe


def create_app(
    settings: Settings | None = None,
    *,
    store: ObjectStore | None = None,
    engine: Engine | None = None,
) -> FastAPI:
    """Build the API for `settings` (default: from the environment); `store`/`engine` override the
    settings'."""
    settings = settings or get_settings()
    # 50+ concurrent progress pollers share the pool with SSE pollers: a bigger pool than SQLAlchemy's 5+10.
    # No pre-ping: it is one more round trip per request (a third of a progress poll). After a Postgres
    # restart the first request on a dead connection gets a 503, SQLAlchemy invalidates the pool, and the
    # next requests reconnect.
    engine_kwargs: dict[str, int | bool] = (
        {}
        if settings.is_sqlite
        else {"pool_size": 20, "max_overflow": 20, "pool_pre_ping": False, "pool_recycle": 1800}
    )
    engine = engine or make_engine(settings.database_url, **engine_kwargs)
    store = store if store is not None else open_store(settings.storage_url, settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        sweep_orphans(UPLOAD_KINDS)  # upload folders of an API (or mesh reader) killed mid-upload
        yield
        app.state.designer.close()
        redis = app.state.redis
        if redis is not None:
            redis.close()
        engine.dispose()

    app = FastAPI(
        title="Omnidata API",
        version=API_VERSION,
        description=(
            "Steerable multi-task vision datasets from 3D scans. Every route but /health needs "
            "`Authorization: Bearer <token>`; a tenant only sees its own spaces, jobs and outputs."
        ),
        openapi_tags=OPENAPI_TAGS,
        lifespan=lifespan,
        docs_url=None,  # FastAPI's pages load Swagger UI and ReDoc from a CDN: /docs is served offline below
        redoc_url=None,
    )
    _set_state(app, settings, engine, store)
    install_error_handlers(app)
    app.add_middleware(RequestGuard, settings=settings)  # token and size checked before a body is read
    app.add_middleware(QueryTokenScrubber)  # ?token= never reaches a log line
    app.add_middleware(SecurityHeaders, settings=settings)  # CSP, no framing, nosniff
    routers = (ops_router, spaces_router, jobs_router, views_router, outputs_router, progress_router,
               workers_router, designer_router)
    for router in routers:
        app.include_router(router)
    mount_dashboard(app)
    mount_docs(app)

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/ui/")

    return app


GIL_SWITCH_INTERVAL_S = 0.001  # Python's default is 5 ms


def app_from_env() -> FastAPI:
    """Factory for `uvicorn --factory services.api.app:app_from_env` (settings from OMNIDATA_* variables).

    The served process hands the GIL around every millisecond instead of every 5: the event loop (/health,
    event streams) waits for it behind the request threads (uploads' packing and storing, database calls), and
    each wait could last a whole interval per busy thread."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    return create_app(get_settings())
