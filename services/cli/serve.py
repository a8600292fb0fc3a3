"""`omnidata serve`: run the REST API and dashboard with uvicorn (settings from OMNIDATA_* variables)."""

from __future__ import annotations

import argparse

from services.cli import CliError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata serve`."""
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    parser.add_argument("--workers", type=int, default=1, help="uvicorn worker processes (default 1)")
    parser.add_argument("--migrate", action="store_true", help="upgrade the database schema before serving")
    parser.add_argument(
        "--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"]
    )


def run(args: argparse.Namespace) -> int:
    """Start uvicorn on the app factory; returns when the server stops."""
    import uvicorn

    from services.core.db.engine import migrate, require_schema, wait_for_database
    from services.core.settings import load_settings

    if not 0 < args.port < 65536:
        raise CliError(f"--port {args.port} is not a TCP port (1-65535)")
    if args.workers < 1:
        raise CliError("--workers must be at least 1")
    settings = load_settings()
    if not settings.api_tokens:
        print("omnidata serve: warning: OMNIDATA_API_TOKENS is empty, every request but /health will get 401")
    if args.migrate:
        wait_for_database(lambda: migrate(settings.database_url), settings.db_wait_s)
    require_schema(settings.database_url, settings.db_wait_s)
    uvicorn.run(
        "services.api.app:app_from_env",
        factory=True,
        host=args.host,
        port=args.port,
        workers=args.workers,
        log_level=args.log_level,
        proxy_headers=True,
        timeout_graceful_shutdown=5,  # SSE streams never end by themselves
    )
    return 0
