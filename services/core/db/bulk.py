"""Fast bulk writes in the caller's transaction: COPY on Postgres, chunked executemany on SQLite.

Planning a job writes up to millions of task rows; the ORM's unit of work is far too slow for that, so
rows go straight to the table (the identity map is bypassed).
"""

from __future__ import annotations

import functools
import io
import json
from collections.abc import Mapping, Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import JSON, Table, TextClause, bindparam, insert, text
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection
from sqlalchemy.orm import DeclarativeBase, Session

from services.core.db.models import UTCDateTime

_SQLITE_CHUNK = 50_000  # rows per executemany, bounds memory of the parameter list


def connection_of(session_or_conn: Session | Connection) -> Connection:
    if isinstance(session_or_conn, Session):
        session_or_conn.flush()  # pending ORM rows (a new job) must exist before rows that reference them
        return session_or_conn.connection()
    return session_or_conn


def table_of(model_or_table: type[DeclarativeBase] | Table) -> Table:
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
    table = table_of(model_or_table)
    names, cols = _columns(rows)
    n = len(cols[0]) if cols else 0
    if n == 0:
        return 0
    unknown = [c for c in names if c not in table.c]
    if unknown:
        raise ValueError(f"bulk_insert: {table.name} has no column(s) {', '.join(unknown)}")
    conn = connection_of(session_or_conn)
    if conn.dialect.name == "postgresql":
        _copy_postgres(conn, table, names, cols)
    else:
        stmt = insert(table)
        for start in range(0, n, _SQLITE_CHUNK):
            part = zip(*(c[start : start + _SQLITE_CHUNK] for c in cols), strict=True)
            conn.execute(stmt, [dict(zip(names, vals, strict=True)) for vals in part])
    return n


_COPY_ESCAPES = str.maketrans({"\\": "\\\\", "\t": "\\t", "\n": "\\n", "\r": "\\r"})


def _copy_text(value: object) -> str:
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
        if isinstance(ctype, JSON) or isinstance(
            getattr(ctype, "_variant_mapping", {}).get("postgresql"), JSON
        ):
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


# Upserts are SQL text built once per shape: SQLAlchemy cannot cache the compiled form of its INSERT ... ON
# CONFLICT DO UPDATE construct, and compiling it anew on every heartbeat cost more CPU than the database
# spent.
@functools.cache
def _upsert_sql(dialect: str, table: Table, columns: tuple[str, ...], key: tuple[str, ...],
                insert_only: tuple[str, ...]) -> TextClause:
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


_DIALECTS = {"postgresql": postgresql.dialect(), "sqlite": sqlite.dialect()}  # type: ignore[no-untyped-call]


def upsert(
    session: Session | Connection, model_or_table: type[DeclarativeBase] | Table, row: Mapping[str, object],
    key: Sequence[str], insert_only: Sequence[str] = (),
) -> None:
    """INSERT `row`, or where its `key` exists UPDATE every other column but `insert_only`: one statement."""
    table = table_of(model_or_table)
    conn = connection_of(session)
    conn.execute(_upsert_sql(conn.dialect.name, table, tuple(row), tuple(key), tuple(insert_only)), dict(row))
