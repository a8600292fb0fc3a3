"""Alembic migrations: upgrade, downgrade to base and back on a fresh Postgres database; models match."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect, text

from services.core.db.engine import (
    MIGRATIONS_DIR,
    SCHEMA_HEAD,
    _create_sqlite_at_head,
    alembic_config,
    downgrade,
    make_engine,
    migrate,
    schema_problem,
)
from services.core.db.models import Base
from tests.conftest import create_pg_database, drop_pg_database

TABLES = {
    "space", "job", "job_space", "job_counter", "camera", "point", "view", "task", "worker", "worker_block",
    "view_output", "compacted_duration",
}


def _tables(url: str) -> set[str]:
    engine = make_engine(url)
    try:
        return set(inspect(engine).get_table_names()) - {"alembic_version"}
    finally:
        engine.dispose()


def _diff(url: str, server_defaults: bool) -> list[object]:
    """What autogenerate would change to make the database match the models (nothing, when in sync)."""
    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            ctx = MigrationContext.configure(
                conn, opts={"compare_type": True, "compare_server_default": server_defaults}
            )
            return list(compare_metadata(ctx, Base.metadata))
    finally:
        engine.dispose()


def _revision(url: str) -> str | None:
    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()
    finally:
        engine.dispose()


@pytest.fixture()
def fresh_pg() -> Iterator[str]:
    """An empty Postgres database of its own (not the session's migrated one)."""
    url = create_pg_database(prefix="omnidata_mig")
    try:
        yield url
    finally:
        drop_pg_database(url)


def _head() -> str:
    heads = ScriptDirectory.from_config(alembic_config()).get_heads()
    assert len(heads) == 1, f"migrations have several heads: {heads}"
    return heads[0]


def test_single_linear_history() -> None:
    script = ScriptDirectory.from_config(alembic_config())
    assert Path(script.dir) == MIGRATIONS_DIR
    revs = list(script.walk_revisions())
    assert revs[-1].revision == "0001" and revs[-1].down_revision is None
    assert len(script.get_heads()) == 1


def test_upgrade_downgrade_upgrade_postgres(fresh_pg: str) -> None:
    assert _tables(fresh_pg) == set()
    migrate(fresh_pg)
    assert _tables(fresh_pg) == TABLES
    assert _revision(fresh_pg) == _head()
    assert _diff(fresh_pg, server_defaults=True) == []
    migrate(fresh_pg)  # idempotent
    downgrade(fresh_pg, "base")
    assert _tables(fresh_pg) == set()
    assert _revision(fresh_pg) is None
    migrate(fresh_pg, "0001")  # step by step as well
    assert _revision(fresh_pg) == "0001"
    migrate(fresh_pg)
    assert _tables(fresh_pg) == TABLES
    assert _diff(fresh_pg, server_defaults=True) == []
    engine = make_engine(fresh_pg)
    try:
        with engine.connect() as conn:  # autoincrement ids are BIGINT identities on Postgres
            kind = conn.execute(
                text(
                    "SELECT data_type FROM information_schema.columns WHERE table_name='task' AND "
                    "column_name='id'"
                )
            ).scalar()
            assert kind == "bigint"
    finally:
        engine.dispose()


def test_concurrent_migrations_on_postgres_wait_for_each_other(fresh_pg: str, repo_root: Path) -> None:
    """API and scheduler starting together: one migrates, the other waits on the lock (polled, so 0004's
    CREATE INDEX CONCURRENTLY is not left waiting on it) and then finds nothing to do."""
    migrate(fresh_pg, "0003")
    # Alembic's context is per process
    code = f"from services.core.db.engine import migrate; migrate({fresh_pg!r})"
    procs = [subprocess.Popen([sys.executable, "-c", code], cwd=repo_root, stderr=subprocess.PIPE, text=True)
             for _ in range(3)]
    for p in procs:
        _, err = p.communicate(timeout=180)
        assert p.returncode == 0, err
    assert _revision(fresh_pg) == _head()
    assert _diff(fresh_pg, server_defaults=True) == []
    engine = make_engine(fresh_pg)
    try:
        with engine.connect() as conn:  # built concurrently and valid; the replaced index is gone
            valid = dict(
                conn.execute(
                    text(
                        "SELECT c.relname, i.indisvalid FROM pg_index AS i JOIN pg_class AS c ON c.oid = "
                        "i.indexrelid "
                        "WHERE c.relname IN ('ix_task_pending_job_id_cue_id', 'ix_task_job_id_state_cue_id')"
                    )
                ).all()
            )
            assert valid == {"ix_task_pending_job_id_cue_id": True}
            assert (
                conn.execute(text(  # this database's: other tests on the server hold their own
                    "SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND database = "
                    "(SELECT oid FROM pg_database WHERE datname = current_database())")).scalar() == 0
            )
    finally:
        engine.dispose()


def test_migrate_creates_a_fresh_sqlite_file(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'new' / 'dir' / 'omnidata.db'}"
    migrate(url)
    assert (tmp_path / "new" / "dir" / "omnidata.db").is_file()
    assert _tables(url) == TABLES
    assert _diff(url, server_defaults=False) == []
    downgrade(url, "base")
    assert _tables(url) == set()
    migrate(url)
    assert _tables(url) == TABLES


def _sqlite_schema(url: str) -> set[tuple[str, str, str, str | None]]:
    """Every table and index of a SQLite database as its CREATE statement (a table name quoted by a rebuild,
    as Alembic's batch operations leave it, unquoted: the same name)."""
    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            rows = conn.execute(text("SELECT type, name, tbl_name, sql FROM sqlite_master")).all()
    finally:
        engine.dispose()
    return {(kind, name, table, sql and sql.replace(f'CREATE TABLE "{name}"', f"CREATE TABLE {name}"))
            for kind, name, table, sql in rows}


def test_a_new_sqlite_file_is_made_at_the_head_as_alembic_makes_it_without_loading_alembic(
    repo_root: Path, tmp_path: Path
) -> None:
    """The embedded default's new database comes from the models, stamped at the head, without importing
    Alembic (0.12-0.17 CPU-s of every `generate`'s start-up): every table, index and the version table as
    Alembic's upgrade of an empty file writes them, and at the revision the schema check wants."""
    assert SCHEMA_HEAD == _head()
    by_alembic = f"sqlite:///{tmp_path / 'alembic.db'}"
    command.upgrade(alembic_config(by_alembic), "head")
    fresh = f"sqlite:///{tmp_path / 'fresh.db'}"
    code = (
        f"import sys; from services.core.db.engine import migrate; migrate({fresh!r}); "
        "print('alembic' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=repo_root, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
    assert _sqlite_schema(fresh) == _sqlite_schema(by_alembic)
    # the database built beside was linked, then removed
    assert not [p for p in tmp_path.iterdir() if ".new-" in p.name]
    engine = make_engine(fresh)
    try:
        assert schema_problem(engine) is None
    finally:
        engine.dispose()
    migrate(fresh)  # an existing file: Alembic's upgrade, nothing to do
    assert _revision(fresh) == _head()


def test_a_database_another_process_created_meanwhile_is_left_as_it_is(tmp_path: Path) -> None:
    path = tmp_path / "state.db"
    path.write_bytes(b"another process's database")
    assert _create_sqlite_at_head(path) is False
    assert path.read_bytes() == b"another process's database"
    assert [p.name for p in tmp_path.iterdir()] == ["state.db"]


def test_alembic_command_line_takes_the_url_from_settings(repo_root: Path, tmp_path: Path) -> None:
    db = tmp_path / "cli.db"
    env = {**os.environ, "OMNIDATA_DATABASE_URL": f"sqlite:///{db}"}
    out = subprocess.run(
        [sys.executable, "-m", "alembic", "-c", str(repo_root / "alembic.ini"), "upgrade", "head"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert _revision(f"sqlite:///{db}") == _head()


def test_upgrading_a_sqlite_file_keeps_the_rows_that_reference_a_job(tmp_path: Path) -> None:
    """0007 rebuilds the job table on SQLite; with foreign keys enforced, dropping the old one would have
    cascaded to every row that references a job (an embedded run's tasks, counters, blocks)."""
    url = f"sqlite:///{tmp_path / 'old.db'}"
    migrate(url, "0006")
    engine = make_engine(url)
    try:
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO job (id, owner, name, spec, state) "
                              "VALUES (1, 'o', 'n', '{}', 'running')"))
            conn.execute(text("INSERT INTO worker_block (worker_id, job_id, failures) VALUES ('w', 1, 2)"))
        migrate(url)
        with engine.connect() as conn:
            assert conn.execute(text("SELECT id, state, paused_by FROM job")).all() == [(1, "running", None)]
            assert conn.execute(text("SELECT worker_id, failures FROM worker_block")).all() == [("w", 2)]
            assert conn.execute(text("PRAGMA foreign_keys")).scalar_one() == 1
    finally:
        engine.dispose()
