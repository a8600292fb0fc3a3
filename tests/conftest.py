"""Shared fixtures: real Postgres, Redis and an S3 endpoint over HTTP (STYLE.md items 10, 11).

Nothing is skipped when a service is down: the fixture fails with a message (`make services` starts them).
Database tests run the Alembic migrations once per session and roll back each test's work.
Tests that need Blender (bpy, in this process or in the commands they run) are marked `bpy`:
`pytest -m "not bpy"` runs the pure ones; with OMNIDATA_TEST_WITHOUT_BPY=1 importing bpy here fails, to prove
it.
"""

from __future__ import annotations

import importlib.abc
import os
import re
import secrets
import shutil
import socket
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest
from _pytest.mark.expression import Expression
from sqlalchemy import Connection, Engine, create_engine, text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session

from services.core.db.engine import make_engine, migrate
from services.core.settings import Settings, get_settings
from services.core.storage import LocalStore

pytest_plugins = ["tests.fixtures.cpu_report"]  # --cpu-report N


class _NoBpy(importlib.abc.MetaPathFinder):
    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == "bpy" or name.startswith("bpy."):
            raise ModuleNotFoundError(
                "bpy is blocked by OMNIDATA_TEST_WITHOUT_BPY (a test not marked bpy needs it)"
            )


if os.environ.get("OMNIDATA_TEST_WITHOUT_BPY"):
    sys.meta_path.insert(0, _NoBpy())

# The user's caches (services.core.user_cache: meshed clouds, parsed spaces, curvature) go to a folder of this
# session, never the real home; the `omnidata` commands the tests run inherit it.
_USER_DATA_DIR = tempfile.mkdtemp(prefix="omnidata-test-user-")
os.environ["OMNIDATA_DATA_DIR"] = _USER_DATA_DIR
# Every `generate` a test runs is cold and leaves no warm-start server behind (services.cli.warm_start), but
# in tests/cli/test_warm_start.py, which turns it on with a folder of its own.
os.environ["OMNIDATA_WARM_START"] = "0"


def pytest_unconfigure(config: pytest.Config) -> None:
    shutil.rmtree(_USER_DATA_DIR, ignore_errors=True)


_BPY_MODULE = re.compile(r"^pytestmark = .*pytest\.mark\.bpy\b", re.MULTILINE)


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """Do not even import a module marked `bpy` as a whole when the -m expression deselects bpy tests."""
    expr = config.option.markexpr
    if not expr or collection_path.suffix != ".py" or not collection_path.name.startswith("test_"):
        return None
    if Expression.compile(expr).evaluate(lambda name: name == "bpy"):
        return None
    return True if _BPY_MODULE.search(collection_path.read_text(encoding="utf-8")) else None


# Fixtures that render with Blender (here or in an `omnidata generate` they run): their tests are `bpy` tests.
BPY_FIXTURES = frozenset(
    {"tiny_banana", "small_job", "trajectory_job", "banana_run", "room_passes", "banana_passes"}
)


# Fixtures of the shared Redis server (a database flushed per test; a deployment's, flushed per module, whose
# tests kill its clients): under pytest-xdist (`make test` runs two or more processes) their tests form one
# group, run one at a time by one process, so a flush or a kill never lands on another test's connection.
SERVICE_FIXTURES = frozenset({"redis_url", "deployment"})


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark `bpy` the tests that use a rendering fixture (before -m selects); group the shared-Redis tests."""
    for item in items:
        fixtures = set(getattr(item, "fixturenames", ()))
        if BPY_FIXTURES & fixtures:
            item.add_marker(pytest.mark.bpy)
        if SERVICE_FIXTURES & fixtures:
            item.add_marker(pytest.mark.xdist_group("services"))


REPO_ROOT = Path(__file__).resolve().parents[1]
PG_ADMIN_URL = os.environ.get("OMNIDATA_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
REDIS_TEST_URL = os.environ.get("OMNIDATA_TEST_REDIS_URL", "redis://127.0.0.1:6379/15")


def _reachable(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=2):
            return True
    except OSError:
        return False


def _need(host: str, port: int, what: str) -> None:
    if not _reachable(host, port):
        pytest.fail(f"{what} is not reachable on {host}:{port}; start it with `make services`", pytrace=False)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root (the folder holding pyproject.toml)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def scenes_dir(repo_root: Path) -> Path:
    """The test scenes: <repo>/../shared/scenes (CI clones the repo with shared/ beside it)."""
    d = (repo_root.parent / "shared" / "scenes").resolve()
    if not d.is_dir():
        pytest.fail(f"test scenes not found at {d}: check out shared/ next to the repository", pytrace=False)
    return d


@dataclass(frozen=True)
class GeneratedRun:
    """What one `omnidata generate` wrote, and what it printed."""

    out: Path
    stdout: str
    tmpdir: Path | None = None  # the run's TMPDIR, when it had one of its own


@pytest.fixture(scope="session")
def tiny_banana(tmp_path_factory: pytest.TempPathFactory, scenes_dir: Path) -> GeneratedRun:
    """One real `omnidata generate` of the banana shared by the embedded, dataset, gallery and end-to-end
    tests: 2 points x 2 wide-baseline views (WIDE), every default cue, 32 px, seed 7, component 'tiny', 2
    workers. Tests only read it (copy it before changing anything)."""
    from tests.fixtures.cli import WIDE, omnidata

    out = tmp_path_factory.mktemp("tiny_banana") / "banana"
    spec = out.parent / "tiny.yaml"
    spec.write_text(WIDE)
    tmpdir = out.parent / "tmp"  # its own, so a test can see what the run leaves in the temp dir
    tmpdir.mkdir()
    res = omnidata(
        "generate", scenes_dir / "ycb_banana", "--out", out, "--spec", spec, "--seed", 7, "--workers", 2,
        "--name", "tiny", "--no-progress", env={"TMPDIR": str(tmpdir)},
    )
    assert res.returncode == 0, res.stderr
    return GeneratedRun(out, res.stdout, tmpdir)


@pytest.fixture(scope="session")
def banana_capture_folder(
    tmp_path_factory: pytest.TempPathFactory, scenes_dir: Path
) -> tuple[Path, Any, Any]:
    """tests.fixtures.photo_capture.banana_capture made once: (folder, loaded space, world frames), read
    only."""
    from tests.fixtures.photo_capture import banana_capture

    folder = tmp_path_factory.mktemp("capture") / "banana_capture"
    space, frames = banana_capture(scenes_dir / "ycb_banana" / "textured_simple_reoriented.obj", folder)
    return folder, space, frames


# ------------------------------------------------------------------------------------------------ Postgres


def create_pg_database(admin_url: str = PG_ADMIN_URL, prefix: str = "omnidata_test") -> str:
    """Create an empty database `<prefix>_<pid>_<rand>` and return its URL."""
    u = make_url(admin_url)
    _need(u.host or "127.0.0.1", u.port or 5432, "PostgreSQL")
    name = f"{prefix}_{os.getpid()}_{secrets.token_hex(4)}"
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
    finally:
        admin.dispose()
    return u.set(database=name).render_as_string(hide_password=False)


def drop_pg_database(url: str, admin_url: str = PG_ADMIN_URL) -> None:
    """Drop the database at `url`, disconnecting whoever still uses it."""
    name = make_url(url).database
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    finally:
        admin.dispose()


@pytest.fixture()
def empty_pg_url() -> Iterator[str]:
    """A fresh Postgres database that nobody migrated."""
    url = create_pg_database()
    try:
        yield url
    finally:
        drop_pg_database(url)


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    """URL of a fresh, migrated Postgres database for this test session (dropped at the end)."""
    url = create_pg_database()
    try:
        migrate(url)
        yield url
    finally:
        drop_pg_database(url)


@pytest.fixture(scope="session")
def pg_engine(pg_url: str) -> Iterator[Engine]:
    """Engine on the session's Postgres database."""
    engine = make_engine(pg_url)
    yield engine
    engine.dispose()


def truncate_all(engine: Engine) -> None:
    """Empty every table: other tests (API, end-to-end) commit for real on the shared database."""
    from services.core.db.models import Base

    names = ", ".join(f'"{t.name}"' for t in Base.metadata.sorted_tables)
    with engine.begin() as conn:
        conn.exec_driver_sql(f"TRUNCATE {names} RESTART IDENTITY CASCADE")


@contextmanager
def rolled_back(engine: Engine) -> Iterator[Connection]:
    """A connection to an emptied database inside a transaction that is rolled back at the end.

    Sessions bound to it with join_transaction_mode="create_savepoint" turn their commits into savepoints.
    """
    truncate_all(engine)
    conn = engine.connect()
    outer = conn.begin()
    try:
        yield conn
    finally:
        outer.rollback()
        conn.close()


@pytest.fixture()
def db_session(pg_engine: Engine) -> Iterator[Session]:
    """A Session on an empty database inside a transaction rolled back after the test (commits become
    savepoints)."""
    with rolled_back(pg_engine) as conn:
        session = Session(bind=conn, join_transaction_mode="create_savepoint", expire_on_commit=False)
        try:
            yield session
        finally:
            session.close()


# ------------------------------------------------------------------------------------------------ SQLite


@pytest.fixture()
def sqlite_url(tmp_path: Path) -> str:
    """URL of a fresh, migrated SQLite database file under tmp_path."""
    url = f"sqlite:///{tmp_path / 'omnidata.db'}"
    migrate(url)
    return url


@pytest.fixture()
def sqlite_session(sqlite_url: str) -> Iterator[Session]:
    """A Session on a fresh migrated SQLite file (committed work stays in that file)."""
    engine = make_engine(sqlite_url)
    session = Session(bind=engine, expire_on_commit=False)
    try:
        yield session
    finally:
        session.close()
        engine.dispose()


# ------------------------------------------------------------------------------------------------ Redis


@pytest.fixture()
def redis_url() -> Iterator[str]:
    """redis://127.0.0.1:6379/15, flushed before and after the test."""
    import redis

    u = urlparse(REDIS_TEST_URL)
    _need(u.hostname or "127.0.0.1", u.port or 6379, "Redis")
    client = redis.Redis.from_url(REDIS_TEST_URL)
    client.flushdb()
    try:
        yield REDIS_TEST_URL
    finally:
        client.flushdb()
        client.close()


# ------------------------------------------------------------------------------------------------ S3


@dataclass
class S3Server:
    """A running S3 endpoint (moto over HTTP) with one bucket, and the settings that point at it."""

    endpoint_url: str
    bucket: str
    region: str = "us-east-1"
    access_key: str = "test-access-key"
    secret_key: str = "test-secret-key"
    env: dict[str, str] = field(default_factory=dict)

    def settings(self, prefix: str = "", **overrides: object) -> Settings:
        """Settings whose storage_url is s3://bucket/prefix on this endpoint."""
        values: dict[str, object] = {
            "storage_url": f"s3://{self.bucket}/{prefix}".rstrip("/"),
            "s3_endpoint_url": self.endpoint_url,
            "s3_region": self.region,
            "aws_access_key_id": self.access_key,
            "aws_secret_access_key": self.secret_key,
        }
        values.update(overrides)
        return get_settings(**values)


@pytest.fixture(scope="session")
def s3_server() -> Iterator[S3Server]:
    """moto's ThreadedMotoServer on 127.0.0.1 (free port, plain HTTP) with a bucket; boto3 talks to it as to
    S3."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    s3 = S3Server(endpoint_url=f"http://{host}:{port}", bucket=f"omnidata-test-{secrets.token_hex(4)}")
    s3.env = {
        "OMNIDATA_STORAGE_URL": f"s3://{s3.bucket}",
        "OMNIDATA_S3_ENDPOINT_URL": s3.endpoint_url,
        "OMNIDATA_S3_REGION": s3.region,
        "OMNIDATA_AWS_ACCESS_KEY_ID": s3.access_key,
        "OMNIDATA_AWS_SECRET_ACCESS_KEY": s3.secret_key,
    }
    client = boto3.client(
        "s3", endpoint_url=s3.endpoint_url, region_name=s3.region,
        aws_access_key_id=s3.access_key, aws_secret_access_key=s3.secret_key,
    )
    client.create_bucket(Bucket=s3.bucket)
    try:
        yield s3
    finally:
        server.stop()


@pytest.fixture()
def local_store(tmp_path: Path) -> LocalStore:
    """A LocalStore rooted in a fresh folder."""
    return LocalStore(tmp_path / "objects")
