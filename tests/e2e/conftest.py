"""A real distributed deployment on this machine: Postgres, Redis, an S3 endpoint (moto over HTTP), and the
service processes started as users start them (`omnidata serve`, `omnidata scheduler`, `omnidata worker` x 2),
configured only through OMNIDATA_* environment variables.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import redis
from sqlalchemy import Engine, text
from sqlalchemy.orm import Session, sessionmaker

from services.cli.token_create import new_token
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.settings import Settings, hash_token
from services.core.storage import ObjectStore, open_store
from tests.conftest import S3Server, create_pg_database, drop_pg_database

REPO = Path(__file__).resolve().parents[2]
# Flushed per module. `make test` gives the run of the `alone` tests, beside the rest, a database of its own.
REDIS_DB_URL = os.environ.get("OMNIDATA_TEST_E2E_REDIS_URL") or os.environ.get("OMNIDATA_TEST_REDIS_URL",
                                                                               "redis://127.0.0.1:6379/13")
LEASE_S = 10  # short leases: a killed worker's task comes back within seconds
WORKER_APP = "omnidata-e2e-worker"
SCHEDULER_APP = "omnidata-e2e-scheduler"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Proc:
    """A started service process with its log file."""

    name: str
    popen: subprocess.Popen[bytes]
    log: Path

    def alive(self) -> bool:
        return self.popen.poll() is None

    def tail(self, n: int = 4000) -> str:
        return self.log.read_text(errors="replace")[-n:] if self.log.exists() else ""

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 20) -> None:
        """Signal the whole process group (the Celery parent and its children) and wait."""
        self.send(sig)
        self.wait(timeout)

    def send(self, sig: int) -> None:
        """Signal the whole process group (if it is still running)."""
        if self.alive():
            try:
                os.killpg(self.popen.pid, sig)
            except ProcessLookupError:
                pass

    def wait(self, timeout: float = 20) -> None:
        """Wait for the process to exit; kill its group when it takes longer than `timeout`."""
        try:
            self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait(timeout=10)

    def children(self) -> list[int]:
        """Pids of the direct children (the Celery pool processes)."""
        path = Path(f"/proc/{self.popen.pid}/task/{self.popen.pid}/children")
        try:
            return [int(p) for p in path.read_text().split()]
        except OSError:
            return []


@dataclass
class Cluster:
    """Where the deployment's state lives, its processes, and helpers to start more of them."""

    env: dict[str, str]
    settings: Settings
    pg_url: str
    engine: Engine
    sm: sessionmaker[Session]
    store: ObjectStore
    prefix: str
    workdir: Path
    token: str
    procs: list[Proc] = field(default_factory=list)
    api_url: str | None = None

    def start(self, name: str, *args: str, app_name: str | None = None, **env: str) -> Proc:
        log = self.workdir / f"{name}.log"
        e = dict(self.env, **env)
        if app_name:
            e["PGAPPNAME"] = app_name  # libpq: lets the test find (and kill) this process's connections
        p = subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=REPO, env=e,
                             stdout=log.open("ab"), stderr=subprocess.STDOUT, start_new_session=True)
        proc = Proc(name, p, log)
        self.procs.append(proc)
        return proc

    def start_worker(self, name: str, **env: str) -> Proc:
        return self.start(name, "worker", "--concurrency", "1", "--render-threads", "1", "--loglevel", "INFO",
                          "--hostname", f"{name}@%h", app_name=WORKER_APP, **env)  # worker id: name@host

    def start_scheduler(self, **env: str) -> Proc:
        return self.start("scheduler", "scheduler", "--interval", "0.3", app_name=SCHEDULER_APP, **env)

    def start_api(self) -> str:
        port = free_port()
        self.start("api", "serve", "--port", str(port), "--log-level", "warning")
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        import httpx

        while True:
            try:
                if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "the API did not start: " + self.procs[-1].tail()
            time.sleep(0.3)
        self.api_url = url
        return url

    def stop_all(self) -> None:
        """SIGTERM every process, then wait for them all (their warm shutdowns overlap)."""
        for p in self.procs:
            p.send(signal.SIGTERM)
        for p in self.procs:
            p.wait()

    def logs(self) -> str:
        return "\n".join(f"===== {p.name} =====\n{p.tail()}" for p in self.procs)

    def terminate_connections(self, app_name: str) -> int:
        """pg_terminate_backend of every connection to the cluster's database opened by `app_name`."""
        admin = make_engine(self.pg_url.rsplit("/", 1)[0] + "/postgres", isolation_level="AUTOCOMMIT")
        try:
            with admin.connect() as c:
                rows = c.execute(text(
                    "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                    "WHERE datname = :db AND application_name = :app AND pid <> pg_backend_pid()"
                ), {"db": self.pg_url.rsplit("/", 1)[1], "app": app_name}).all()
                return len(rows)
        finally:
            admin.dispose()


def redis_up(port: int) -> bool:
    return subprocess.run(["redis-cli", "-p", str(port), "ping"], capture_output=True).returncode == 0


def wait_for_redis(port: int, up: bool) -> None:
    deadline = time.monotonic() + 20
    while redis_up(port) != up:
        assert time.monotonic() < deadline, f"redis on :{port} did not {'start' if up else 'stop'}"
        time.sleep(0.1)


def start_redis(port: int, folder: Path) -> None:
    """A redis-server on `port` as the CI machine runs its own (no persistence), logging into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        [
            "redis-server", "--daemonize", "yes", "--bind", "127.0.0.1", "--port", str(port), "--save", "",
            "--appendonly", "no", "--dir", str(folder), "--logfile", str(folder / "redis.log"),
        ],
        check=True, capture_output=True, timeout=20,
    )
    wait_for_redis(port, up=True)


def stop_redis(port: int) -> None:
    """Stop it without saving: every message it held is lost."""
    subprocess.run(["redis-cli", "-p", str(port), "shutdown", "nosave"], capture_output=True, timeout=20)
    wait_for_redis(port, up=False)


@pytest.fixture()
def own_redis(tmp_path: Path) -> Iterator[int]:
    """The port of a Redis server of the test's own: restarting it drops no other test's connections (the
    suite runs in several processes, tests/conftest.py)."""
    port = free_port()
    start_redis(port, tmp_path / "redis")
    try:
        yield port
    finally:
        stop_redis(port)


@pytest.fixture(scope="module")
def deployment(s3_server: S3Server, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """Per module: a fresh migrated Postgres database, a Redis database and an S3 prefix."""
    url = create_pg_database(prefix="omnidata_e2e")
    migrate(url)
    prefix = f"e2e-{secrets.token_hex(4)}"
    r = redis.Redis.from_url(REDIS_DB_URL)
    r.flushdb()
    r.close()
    try:
        yield {"pg_url": url, "prefix": prefix, "root": tmp_path_factory.mktemp("e2e")}
    finally:
        drop_pg_database(url)


@pytest.fixture()
def bare_cluster(deployment: dict[str, Any], s3_server: S3Server, tmp_path: Path,
                 request: pytest.FixtureRequest) -> Iterator[Cluster]:
    """The deployment's environment with no process started yet (for tests that start theirs with other
    settings); every process started on it is stopped after the test."""
    token = new_token()  # as `omnidata token create` makes them: never starting with '-'
    url, prefix = deployment["pg_url"], deployment["prefix"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("OMNIDATA_")}
    env.update(s3_server.env)
    env.update(
        OMNIDATA_DATABASE_URL=url, OMNIDATA_BROKER_URL=REDIS_DB_URL,
        OMNIDATA_STORAGE_URL=f"s3://{s3_server.bucket}/{prefix}", OMNIDATA_DATA_DIR=str(tmp_path / "data"),
        OMNIDATA_LEASE_S=str(LEASE_S), OMNIDATA_DISPATCH_WINDOW="6", OMNIDATA_RENDER_DEVICE="cpu",
        OMNIDATA_API_TOKENS=json.dumps({hash_token(token): "e2e"}), OMNIDATA_OWNER="e2e",
        PYTHONUNBUFFERED="1",
    )
    settings = s3_server.settings(prefix=prefix, database_url=url, broker_url=REDIS_DB_URL, lease_s=LEASE_S)
    engine = make_engine(url)
    c = Cluster(
        env, settings, url, engine, make_sessionmaker(engine), open_store(settings.storage_url, settings),
        prefix, tmp_path, token,
    )
    try:
        yield c
    finally:
        c.stop_all()
        engine.dispose()
        if request.node.rep_call.failed if hasattr(request.node, "rep_call") else False:
            print(c.logs())


@pytest.fixture()
def cluster(bare_cluster: Cluster) -> Cluster:
    """The deployment with the scheduler and two workers running (stopped after the test)."""
    bare_cluster.start_scheduler()
    bare_cluster.start_worker("worker-a")
    bare_cluster.start_worker("worker-b")
    return bare_cluster


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: Any) -> Iterator[None]:
    # Remember each phase's report on the item, so the cluster fixture can print the logs of a failed test.
    outcome = yield
    rep = outcome.get_result()
    setattr(item, f"rep_{rep.when}", rep)
