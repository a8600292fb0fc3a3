"""`omnidata migrate [--check]`: bring the database schema to this code's Alembic head.

The services (serve, scheduler, worker) refuse to start on a database that is not at the head; this is the
command their refusal names. Configured by OMNIDATA_DATABASE_URL like the services.
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata migrate`."""
    parser.add_argument(
        "--check", action="store_true",
        help="change nothing: exit 0 when the schema is at the head, 1 (with the reason) when not",
    )


def run(args: argparse.Namespace) -> int:
    """Upgrade (or only check) the configured database; prints one line with the outcome."""
    from services.core.db.engine import SchemaNotCurrent, migrate, require_schema, schema_heads
    from services.core.settings import load_settings

    settings = load_settings()
    head = ", ".join(schema_heads())
    try:
        require_schema(settings.database_url)
        print(f"database schema is at the head revision {head}")
        return 0
    except SchemaNotCurrent as e:  # DatabaseUnreachable goes up: one line, exit 2
        if args.check:
            print(f"omnidata migrate: {e}", file=sys.stderr)
            return 1
    migrate(settings.database_url)  # SchemaNotCurrent (one line, exit 2) when Alembic refuses
    print(f"database schema upgraded to revision {head}")
    return 0
