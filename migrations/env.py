"""Alembic environment: the URL comes from `migrate(url)`, `-x url=...`, alembic.ini, or the settings."""

from __future__ import annotations

import time
from logging.config import fileConfig

from alembic import context
from sqlalchemy import pool, text
from sqlalchemy.engine import Connection

from services.core.db.engine import make_engine
from services.core.db.models import Base
from services.core.settings import get_settings

config = context.config
if config.config_file_name is not None:  # the alembic command line; migrate() leaves logging alone
    fileConfig(config.config_file_name, disable_existing_loggers=False)

target_metadata = Base.metadata
# Serialises concurrent `migrate()` calls (API and scheduler starting together) on Postgres.
_PG_LOCK_ID = 0x0A1E_0B1C


def database_url() -> str:
    """The URL to migrate: set by services.core.db.engine.migrate, else -x url=..., else ini, else settings."""
    url = config.attributes.get("url")
    url = url or context.get_x_argument(as_dictionary=True).get("url")
    url = url or config.get_main_option("sqlalchemy.url")
    return str(url or get_settings().database_url)


def _configure(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",  # SQLite ALTERs need table rebuilds
        compare_type=True,
    )


def _lock(connection: Connection) -> None:
    """Take the migration lock for this connection's session (it outlives the commits of an autocommit block).
    Polled, not waited on: a waiting statement holds a snapshot, which CREATE INDEX CONCURRENTLY in the
    running migration would wait for in turn (a deadlock)."""
    while not connection.execute(text(f"SELECT pg_try_advisory_lock({_PG_LOCK_ID})")).scalar():
        connection.commit()
        time.sleep(0.2)
    connection.commit()


def _run(connection: Connection) -> None:
    postgres = connection.dialect.name == "postgresql"
    if postgres:
        _lock(connection)
    try:
        _configure(connection)
        with context.begin_transaction():
            context.run_migrations()
    finally:
        if postgres:
            connection.rollback()  # whatever a failed migration left open, so that the unlock can run
            connection.execute(text(f"SELECT pg_advisory_unlock({_PG_LOCK_ID})"))
            connection.commit()


def run_migrations_offline() -> None:
    """Emit SQL to stdout (`alembic upgrade head --sql`)."""
    context.configure(url=database_url(), target_metadata=target_metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Run against a live database (a connection handed over in attributes, or a fresh engine)."""
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = make_engine(database_url(), poolclass=pool.NullPool)
    try:
        with engine.connect() as conn:
            _run(conn)
            conn.commit()
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
