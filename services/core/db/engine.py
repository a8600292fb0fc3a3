"""Database engines and the schema check: SQLAlchemy engines, Alembic migrations, refusing a stale schema.

Works on Postgres (the service) and SQLite (the embedded default) with the same calls. Bulk writes are in
services.core.db.bulk, the progress counters in services.core.db.counters; task state changes go through
services.core.db.states.transition(), which adjusts the counters in the same transaction.
"""

from __future__ import annotations

import os
import re
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.engine import make_url
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import ConnectionPoolEntry, NullPool

from services.core.settings import ConfigurationError

if TYPE_CHECKING:  # alembic is imported where used: the API and workers start without it
    from alembic.config import Config
    from alembic.script import ScriptDirectory

MIGRATIONS_DIR = Path(__file__).resolve().parents[3] / "migrations"
SCHEMA_HEAD = "0007"  # the head revision of migrations/ (tests/core/db/test_migrations.py keeps them equal)
SQLITE_BUSY_TIMEOUT_MS = 30_000
T = TypeVar("T")
# Alembic's own version table, as its upgrade creates it on SQLite
_ALEMBIC_VERSION_DDL = ("CREATE TABLE alembic_version (\n\tversion_num VARCHAR(32) NOT NULL, \n\t"
                        "CONSTRAINT alembic_version_pkc PRIMARY KEY (version_num)\n)")


def make_engine(url: str, **kwargs: Any) -> Engine:
    """Engine for `url`: SQLite gets WAL, a 30 s busy timeout and foreign keys; Postgres gets
    pool_pre_ping."""
    u = make_url(url)
    if u.get_backend_name() == "sqlite":
        if u.database and u.database != ":memory:":
            Path(u.database).expanduser().parent.mkdir(parents=True, exist_ok=True)
        connect_args = {"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000, "check_same_thread": False}
        connect_args.update(kwargs.pop("connect_args", {}))
        engine = create_engine(url, connect_args=connect_args, **kwargs)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn: DBAPIConnection, _record: ConnectionPoolEntry) -> None:
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")  # readers do not block the writer (API vs workers)
            cur.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA synchronous=NORMAL")  # safe with WAL, much faster commits
            cur.close()

        return engine
    kwargs.setdefault("pool_pre_ping", True)
    return create_engine(url, **kwargs)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """Session factory; objects stay readable after commit (expire_on_commit=False)."""
    return sessionmaker(bind=engine, expire_on_commit=False)


def alembic_config(url: str | None = None) -> Config:
    """Alembic Config pointing at migrations/ without needing alembic.ini; `url` overrides the settings."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url is not None:
        cfg.attributes["url"] = url
    return cfg


def migrate(url: str, revision: str = "head") -> None:
    """Upgrade the database at `url` to `revision` (Alembic `upgrade`); creates a SQLite file if needed (a new
    one at the head directly: _create_sqlite_at_head).

    SchemaNotCurrent when Alembic refuses (e.g. the database is at a revision this code does not know).
    """
    u = make_url(url)
    if u.get_backend_name() == "sqlite" and u.database and u.database != ":memory:":
        path = Path(u.database).expanduser()
        path.parent.mkdir(parents=True, exist_ok=True)
        if revision == "head" and not path.exists() and _create_sqlite_at_head(path):
            return
    from alembic import command
    from alembic.util import CommandError

    try:
        command.upgrade(alembic_config(url), revision)
    except CommandError as e:
        raise SchemaNotCurrent(f"cannot migrate the database: {e}") from None


def _create_sqlite_at_head(path: Path) -> bool:
    """A new SQLite database at `path`: the models' tables stamped at SCHEMA_HEAD, the schema Alembic's
    upgrade of an empty file gives (a test compares them), without loading Alembic (0.12-0.17 CPU-s of every
    embedded run's start-up). Built beside `path` and hard-linked into place, so a database another process
    created meanwhile is never touched: False then, or where the file system has no hard links (Alembic's
    upgrade takes
    over)."""
    from services.core.db.models import Base

    tmp = path.with_name(f".{path.name}.new-{uuid.uuid4().hex}")
    engine = make_engine(f"sqlite:///{tmp}", poolclass=NullPool)
    try:
        with engine.begin() as conn:
            Base.metadata.create_all(conn)
            conn.execute(text(_ALEMBIC_VERSION_DDL))
            conn.execute(text("INSERT INTO alembic_version (version_num) VALUES (:v)"), {"v": SCHEMA_HEAD})
        engine.dispose()  # the last connection closed: the WAL is checkpointed into the file
        try:
            os.link(tmp, path)
        except OSError:  # FileExistsError: another process's database
            return False
        return True
    finally:
        engine.dispose()
        for leftover in (tmp, tmp.with_name(tmp.name + "-wal"), tmp.with_name(tmp.name + "-shm")):
            leftover.unlink(missing_ok=True)


class SchemaNotCurrent(ConfigurationError):
    """The database schema is not at this code's Alembic head; the message names the revisions and the fix."""


class DatabaseUnreachable(ConfigurationError):
    """The database did not answer at start-up; the message names the driver's reason."""


# Refusals no wait fixes: a wrong password or user, no such database. At connect time psycopg gives no
# SQLSTATE (28xxx, 3D000), only the server's FATAL line.
_PERMANENT_REFUSAL = re.compile(
    r"FATAL:\s+(.*authentication failed|role .* does not exist|database .* does not exist|"
    r"no pg_hba\.conf entry)"
)


def _scripts() -> ScriptDirectory:
    from alembic.script import ScriptDirectory

    return ScriptDirectory.from_config(alembic_config())


def schema_heads() -> tuple[str, ...]:
    """The Alembic head revision(s) of this code's migrations/ (what `migrate` upgrades to)."""
    return tuple(sorted(_scripts().get_heads()))


def schema_problem(engine: Engine, heads: Sequence[str] | None = None) -> str | None:
    """None when the database at `engine` is at the code's head revision, else a one-line reason and fix.

    Raises the driver's error when the database cannot be reached (that is not a schema problem).
    """
    from alembic.migration import MigrationContext

    heads = tuple(heads) if heads is not None else schema_heads()
    with engine.connect() as conn:
        current = tuple(sorted(MigrationContext.configure(conn).get_current_heads()))
    if current == heads:
        return None
    fix = "run `omnidata migrate` (or start the API with `omnidata serve --migrate`)"
    if not current:
        return f"the database is not migrated (no schema revision; this code needs {', '.join(heads)}): {fix}"
    known = {script.revision for script in _scripts().walk_revisions()}
    if not set(current) <= known:
        return (f"the database is at schema revision {', '.join(current)}, which this code does not know "
                f"(newer code migrated it?): run the matching omnidata version")
    return (
        f"the database schema is at revision {', '.join(current)}, this code needs {', '.join(heads)}: {fix}"
    )


def require_schema(url: str, wait_s: float = 0.0) -> None:
    """Raise SchemaNotCurrent (one line naming the fix) unless the database at `url` is at the code's head.

    DatabaseUnreachable when it does not answer, after waiting up to `wait_s` for it (wait_for_database).
    """
    def check() -> str | None:
        engine = make_engine(url, poolclass=NullPool)
        try:
            return schema_problem(engine)
        finally:
            engine.dispose()

    problem = wait_for_database(check, wait_s)
    if problem:
        raise SchemaNotCurrent(problem)


def wait_for_database(call: Callable[[], T], wait_s: float) -> T:
    """call() (which opens its own connection), tried again while the database does not answer for up to
    `wait_s` seconds: a service starting during a Postgres restart or failover, or whose connection an
    operator cut, waits instead of exiting. Refusals that waiting cannot fix (a wrong password or user, no
    such database) and the end of the wait raise DatabaseUnreachable naming the driver's reason."""
    deadline = time.monotonic() + wait_s
    delay = 0.1
    told = False
    while True:
        try:
            return call()
        except OperationalError as e:
            reason = str(e.orig or e).strip().splitlines()[0]
            if _PERMANENT_REFUSAL.search(reason) or time.monotonic() + delay > deadline:
                raise DatabaseUnreachable(
                    f"cannot reach the database ({reason}): check OMNIDATA_DATABASE_URL") from None
            if not told:  # one line, not one per try
                print(f"waiting up to {wait_s:g} s for the database ({reason})", file=sys.stderr, flush=True)
                told = True
            time.sleep(delay)
            delay = min(2 * delay, 2.0)


def downgrade(url: str, revision: str = "base") -> None:
    """Downgrade the database at `url` to `revision` (Alembic `downgrade`)."""
    from alembic import command

    command.downgrade(alembic_config(url), revision)



