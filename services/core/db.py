"""Database helpers: engines, migrations, fast bulk inserts and the incremental progress counters.

Works on Postgres (the service) and SQLite (the embedded default) with the same calls. Task state changes go
through services.core.states.transition(), which moves tasks and adjusts `job_counter` (add_counts) in the same
transaction, so progress is read from a handful of counter rows (`job_progress`) instead of COUNT(*); the
rows are sharded (COUNTER_SHARDS per job, cue and state) so that concurrent writers do not queue on one lock.
"""

from __future__ import annotations

import functools
import io
import json
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import JSON, Engine, Table, bindparam, create_engine, event, func, insert, select, text
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, make_url
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker
from sqlalchemy.pool import NullPool

from services.core.models import JobCounter, TaskState, UTCDateTime
from services.core.settings import ConfigurationError

MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"
SQLITE_BUSY_TIMEOUT_MS = 30_000
_IN_CHUNK = 5_000  # ids per UPDATE ... WHERE id IN (...): below SQLite's and psycopg's parameter limits
_SQLITE_CHUNK = 50_000  # rows per executemany, bounds memory of the parameter list


def make_engine(url: str, **kwargs: Any) -> Engine:
    """Engine for `url`: SQLite gets WAL, a 30 s busy timeout and foreign keys; Postgres gets pool_pre_ping."""
    u = make_url(url)
    if u.get_backend_name() == "sqlite":
        if u.database and u.database != ":memory:":
            Path(u.database).expanduser().parent.mkdir(parents=True, exist_ok=True)
        connect_args = {"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000, "check_same_thread": False}
        connect_args.update(kwargs.pop("connect_args", {}))
        engine = create_engine(url, connect_args=connect_args, **kwargs)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
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


def alembic_config(url: str | None = None) -> Any:
    """Alembic Config pointing at migrations/ without needing alembic.ini; `url` overrides the settings."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url is not None:
        cfg.attributes["url"] = url
    return cfg


def migrate(url: str, revision: str = "head") -> None:
    """Upgrade the database at `url` to `revision` (Alembic `upgrade`); creates a SQLite file if needed.

    SchemaNotCurrent when Alembic refuses (e.g. the database is at a revision this code does not know).
    """
    from alembic import command
    from alembic.util import CommandError

    u = make_url(url)
    if u.get_backend_name() == "sqlite" and u.database and u.database != ":memory:":
        Path(u.database).expanduser().parent.mkdir(parents=True, exist_ok=True)
    try:
        command.upgrade(alembic_config(url), revision)
    except CommandError as e:
        raise SchemaNotCurrent(f"cannot migrate the database: {e}") from None


class SchemaNotCurrent(ConfigurationError):
    """The database schema is not at this code's Alembic head; the message names the revisions and the fix."""


class DatabaseUnreachable(ConfigurationError):
    """The database did not answer at start-up; the message names the driver's reason."""


def _scripts() -> Any:
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
    return f"the database schema is at revision {', '.join(current)}, this code needs {', '.join(heads)}: {fix}"


def require_schema(url: str) -> None:
    """Raise SchemaNotCurrent (one line naming the fix) unless the database at `url` is at the code's head.

    DatabaseUnreachable when it does not answer.
    """
    engine = make_engine(url, poolclass=NullPool)
    try:
        problem = schema_problem(engine)
    except OperationalError as e:
        reason = str(e.orig or e).strip().splitlines()[0]
        raise DatabaseUnreachable(f"cannot reach the database ({reason}): check OMNIDATA_DATABASE_URL") from None
    finally:
        engine.dispose()
    if problem:
        raise SchemaNotCurrent(problem)


def downgrade(url: str, revision: str = "base") -> None:
    """Downgrade the database at `url` to `revision` (Alembic `downgrade`)."""
    from alembic import command

    command.downgrade(alembic_config(url), revision)


# ---------------------------------------------------------------------------------------------- bulk insert


def _connection(session_or_conn: Session | Connection) -> Connection:
    if isinstance(session_or_conn, Session):
        session_or_conn.flush()  # pending ORM rows (a new job) must exist before rows that reference them
        return session_or_conn.connection()
    return session_or_conn


def _table(model_or_table: type[DeclarativeBase] | Table) -> Table:
    if isinstance(model_or_table, Table):
        return model_or_table
    table = model_or_table.__table__
    assert isinstance(table, Table)
    return table


def _plain(values: Any) -> list[Any]:
    # numpy arrays/scalars -> Python objects: neither sqlite3 nor psycopg's text COPY wants numpy types
    return list(values.tolist()) if hasattr(values, "tolist") else list(values)


def _columns(rows: Sequence[Mapping[str, Any]] | Mapping[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """Normalise rows (list of dicts, or dict of equal-length columns) to column names + column lists."""
    if isinstance(rows, Mapping):
        names = list(rows)
        cols = [_plain(rows[n]) for n in names]
        lengths = {len(c) for c in cols}
        if len(lengths) > 1:
            sizes = {name: len(c) for name, c in zip(names, cols, strict=True)}
            raise ValueError(f"bulk_insert: columns have different lengths: {sizes}")
        return names, cols
    if not rows:
        return [], []
    names = list(rows[0])
    key_set = set(names)
    for i, r in enumerate(rows):
        if r.keys() != key_set:
            raise ValueError(f"bulk_insert: row {i} has keys {sorted(r)}, expected {sorted(names)}")
    return names, [[r[n] for r in rows] for n in names]


def bulk_insert(
    session_or_conn: Session | Connection,
    model_or_table: type[DeclarativeBase] | Table,
    rows: Sequence[Mapping[str, Any]] | Mapping[str, Any],
) -> int:
    """Insert many rows fast in the caller's transaction; returns the number of rows inserted.

    `rows` is a list of dicts (same keys) or a dict of equal-length column sequences (lists or numpy arrays).
    Postgres: one COPY FROM STDIN (text format). SQLite: executemany of one INSERT. Columns left out take
    their server defaults (autoincrement ids, state 'pending', ...). The ORM identity map is bypassed.
    """
    table = _table(model_or_table)
    names, cols = _columns(rows)
    n = len(cols[0]) if cols else 0
    if n == 0:
        return 0
    unknown = [c for c in names if c not in table.c]
    if unknown:
        raise ValueError(f"bulk_insert: {table.name} has no column(s) {', '.join(unknown)}")
    conn = _connection(session_or_conn)
    if conn.dialect.name == "postgresql":
        _copy_postgres(conn, table, names, cols)
    else:
        stmt = insert(table)
        for start in range(0, n, _SQLITE_CHUNK):
            part = zip(*(c[start : start + _SQLITE_CHUNK] for c in cols), strict=True)
            conn.execute(stmt, [dict(zip(names, vals, strict=True)) for vals in part])
    return n


_COPY_ESCAPES = str.maketrans({"\\": "\\\\", "\t": "\\t", "\n": "\\n", "\r": "\\r"})


def _copy_text(value: Any) -> str:
    """One value in COPY text format (NULL is \\N); strings are escaped."""
    if value is None:
        return "\\N"
    if isinstance(value, bool):
        return "t" if value else "f"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, datetime):
        return value.isoformat()
    return str(value).translate(_COPY_ESCAPES)


def _copy_postgres(conn: Connection, table: Table, names: list[str], cols: list[list[Any]]) -> None:
    # Apply the column types' Python-side conversions (JSON documents, UTC datetimes) before formatting.
    for i, name in enumerate(names):
        ctype = table.c[name].type
        if isinstance(ctype, JSON) or isinstance(getattr(ctype, "_variant_mapping", {}).get("postgresql"), JSON):
            cols[i] = [None if v is None else json.dumps(v, separators=(",", ":")) for v in cols[i]]
        elif isinstance(ctype, UTCDateTime):
            cols[i] = [ctype.process_bind_param(v, conn.dialect) for v in cols[i]]
    quoted = ", ".join(conn.dialect.identifier_preparer.quote(n) for n in names)
    target = conn.dialect.identifier_preparer.format_table(table)
    driver = conn.connection.driver_connection
    assert driver is not None
    # Formatting rows ourselves and sending large text blocks is several times faster than write_row.
    batch = 20_000
    with driver.cursor() as cur, cur.copy(f"COPY {target} ({quoted}) FROM STDIN") as copy:
        n = len(cols[0])
        for start in range(0, n, batch):
            buf = io.StringIO()
            for vals in zip(*(c[start : start + batch] for c in cols), strict=True):
                buf.write("\t".join(map(_copy_text, vals)))
                buf.write("\n")
            copy.write(buf.getvalue())


# ---------------------------------------------------------------------------------------------- counters


# Counter rows per (job, cue, state) that concurrent writers spread over (migration 0003): on Postgres a statement
# adds its deltas to shard (backend pid mod COUNTER_SHARDS), and as a connection runs one transaction at a time,
# two transactions share a row only when their pids collide. SQLite has one writer at a time anyway: shard 0.
COUNTER_SHARDS = 16


# Counter and row upserts are SQL text built once per shape: SQLAlchemy cannot cache the compiled form of its
# INSERT ... ON CONFLICT DO UPDATE construct, and compiling it anew on every claim, result and heartbeat cost
# more CPU than the database spent running it.
@functools.cache
def _add_counts_sql(dialect: str) -> Any:
    shard = f"mod(pg_backend_pid(), {COUNTER_SHARDS})" if dialect == "postgresql" else "0"
    return text(
        f"INSERT INTO job_counter (job_id, cue, state, shard, n) VALUES (:job_id, :cue, :state, {shard}, :n) "
        "ON CONFLICT (job_id, cue, state, shard) DO UPDATE SET n = job_counter.n + excluded.n"
    )


def add_counts(session: Session | Connection, job_id: int, deltas: Mapping[tuple[str, str], int]) -> None:
    """Add `deltas[(cue, state)]` to the job's counters (UPSERT into this connection's shard: n = n + excluded.n);
    zero deltas are skipped."""
    items = sorted((k, d) for k, d in deltas.items() if d)  # fixed order: concurrent upserts lock rows alike
    if not items:
        return
    conn = _connection(session)
    conn.execute(_add_counts_sql(conn.dialect.name),
                 [{"job_id": job_id, "cue": cue, "state": state, "n": d} for (cue, state), d in items])


@functools.cache
def _upsert_sql(dialect: str, table: Table, columns: tuple[str, ...], key: tuple[str, ...],
                insert_only: tuple[str, ...]) -> Any:
    prep = _DIALECTS[dialect].identifier_preparer
    names = ", ".join(prep.quote(c) for c in columns)
    changes = ", ".join(f"{prep.quote(c)} = excluded.{prep.quote(c)}" for c in columns
                        if c not in key and c not in insert_only)
    action = f"DO UPDATE SET {changes}" if changes else "DO NOTHING"
    stmt = text(
        f"INSERT INTO {prep.format_table(table)} ({names}) VALUES ({', '.join(':' + c for c in columns)}) "
        f"ON CONFLICT ({', '.join(prep.quote(c) for c in key)}) {action}"
    )
    return stmt.bindparams(*(bindparam(c, type_=table.c[c].type) for c in columns))


_DIALECTS = {"postgresql": postgresql.dialect(), "sqlite": sqlite.dialect()}


def upsert(
    session: Session | Connection, model_or_table: type[DeclarativeBase] | Table, row: Mapping[str, Any],
    key: Sequence[str], insert_only: Sequence[str] = (),
) -> None:
    """INSERT `row`, or where its `key` exists UPDATE every other column but `insert_only`: one statement."""
    table = _table(model_or_table)
    conn = _connection(session)
    stmt = _upsert_sql(conn.dialect.name, table, tuple(row), tuple(key), tuple(insert_only))
    conn.execute(stmt, dict(row))


def init_counts(session: Session | Connection, job_id: int, pending: Mapping[str, int]) -> None:
    """Record freshly planned tasks: `pending[cue]` tasks of each cue in state 'pending'."""
    add_counts(session, job_id, {(cue, TaskState.PENDING): n for cue, n in pending.items()})


def summed_counters(job_ids: Any) -> Any:
    """SELECT job_id, cue, state, n: the counters of `job_ids` (a list or a correlated column) summed over their
    shards, zero counts left out."""
    c = _table(JobCounter).c
    listed = isinstance(job_ids, list | tuple)
    n = func.sum(c.n)
    stmt = (
        select(c.job_id, c.cue, c.state, n.label("n"))
        .where(c.job_id.in_(job_ids) if listed else c.job_id == job_ids)
        .group_by(c.job_id, c.cue, c.state)
        .having(n != 0)
    )
    return stmt if listed else stmt.correlate(job_ids.table)


def job_progress(session: Session | Connection, job_id: int) -> dict[str, dict[str, int]]:
    """Task counts of a job as {cue: {state: n}}, read from job_counter only (zero counts omitted)."""
    out: dict[str, dict[str, int]] = {}
    sub = summed_counters([job_id]).subquery()
    rows = _connection(session).execute(select(sub.c.cue, sub.c.state, sub.c.n).order_by(sub.c.cue, sub.c.state))
    for cue, state, n in rows:
        out.setdefault(cue, {})[state] = int(n)
    return out
