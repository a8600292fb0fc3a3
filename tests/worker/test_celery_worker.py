"""The Celery side of the worker: configuration, the thin `render.cue` task (called directly), and a real
`omnidata worker` process consuming from Redis, writing to Postgres and the object store, heart-beating and
recycling its child process.
"""

from __future__ import annotations

import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import Engine, select
from sqlalchemy.orm import Session, sessionmaker

from services.cli import CliError
from services.cli.worker import process_layout, worker_argv
from services.core.celery_config import TASK_RENDER_CUE
from services.core.db.engine import make_engine, make_sessionmaker
from services.core.db.models import Task, Worker
from services.core.settings import get_settings
from services.worker import tasks
from services.worker.celery_app import create_app
from services.worker.run.claim import TransientError
from services.worker.run.runner import TaskRunner
from tests.worker.run.test_runner import banana, make_job, queue  # noqa: F401  (banana is a fixture)

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture()
def pg_sm(pg_engine: Engine) -> sessionmaker[Session]:
    return make_sessionmaker(pg_engine)


@pytest.fixture()
def runtime_reset() -> Iterator[None]:
    saved = tasks._runtime
    yield
    tasks._runtime = saved


def test_worker_app_is_configured_for_long_idempotent_tasks():
    s = get_settings(worker_max_tasks=7, worker_max_memory_mb=512, lease_s=900)
    app = create_app(s)
    c = app.conf
    assert TASK_RENDER_CUE in app.tasks
    assert c.task_acks_late and c.task_reject_on_worker_lost and c.worker_prefetch_multiplier == 1
    assert c.broker_connection_retry_on_startup and c.broker_connection_max_retries is None
    assert c.worker_max_tasks_per_child == 7 and c.worker_max_memory_per_child == 512 * 1024
    assert c.broker_transport_options["visibility_timeout"] >= 3600
    assert c.task_serializer == "json" and c.result_backend is None
    argv = worker_argv(
        type("A", (), {"hostname": None, "concurrency": 3, "loglevel": "INFO", "pool": "prefork"})(),
        ["render", "derive"],
    )
    assert "--queues=render,derive" in argv and "--concurrency=3" in argv


def test_default_worker_uses_every_core_one_process_each():
    assert process_layout(None, None, 8) == (8, 1)  # no tuning: every core renders and derives
    assert process_layout(1, None, 8) == (1, 8)  # one process renders with every core
    assert process_layout(2, None, 8) == (2, 4)
    assert process_layout(3, None, 2) == (3, 1)
    assert process_layout(None, 2, 8) == (8, 2)  # render threads as given
    for bad in ((0, None), (None, 0)):
        with pytest.raises(CliError):
            process_layout(*bad, 8)


def test_called_task_runs_the_runner_and_maps_outcomes(pg_sm, banana, runtime_reset):  # noqa: F811
    settings = get_settings(lease_s=60)
    runner = TaskRunner(
        pg_sm, banana.store, settings, "celery-test", cache_dir=banana.cache_dir, render_threads=1
    )
    tasks._runtime = tasks.Runtime(os.getpid(), settings, None, runner, None)
    create_app(settings)
    job_id = make_job(pg_sm, banana)
    tid = queue(pg_sm, job_id, "point_info")
    assert tasks.render_cue.apply(args=[tid]).get() == "done"
    assert tasks.render_cue.apply(args=[tid]).get() == "skipped"  # a duplicate message changes nothing
    assert tasks.render_cue.apply(args=[str(tid)]).get() == "skipped"
    for bad in (None, -3, "x", True, [1]):
        assert tasks.render_cue.apply(args=[bad]).get() == "invalid"
    with pg_sm() as s:
        row = s.get(Task, tid)
        assert row.state == "done" and row.attempts == 1 and row.worker_id == "celery-test"


def test_unreachable_database_is_a_retry_not_a_lost_task(banana, runtime_reset):  # noqa: F811
    settings = get_settings(lease_s=60, database_url="postgresql+psycopg://postgres@127.0.0.1:1/none")
    engine = make_engine(settings.database_url, connect_args={"connect_timeout": 1})
    runner = TaskRunner(make_sessionmaker(engine), banana.store, settings, "w", db_retry_s=0.0)
    with pytest.raises(TransientError, match="could not claim task 5"):
        runner.run(5)
    calls: list[int] = []
    real_run = runner.run

    def counting(task_id: int) -> Any:
        calls.append(task_id)
        return real_run(task_id)

    runner.run = counting  # type: ignore[method-assign]
    tasks._runtime = tasks.Runtime(os.getpid(), settings, engine, runner, None)
    create_app(settings)
    result = tasks.render_cue.apply(args=[5])  # eager: Celery replays the retries at once
    assert result.state == "FAILURE" and isinstance(result.result, TransientError)
    assert len(calls) == tasks.MAX_TRANSIENT_RETRIES + 1
    engine.dispose()


# ------------------------------------------------------------------------------------------ a real worker


def worker_env(pg_url: str, redis_url: str, store_root: Path, data_dir: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("OMNIDATA_")}
    env.update(
        OMNIDATA_DATABASE_URL=pg_url, OMNIDATA_BROKER_URL=redis_url, OMNIDATA_STORAGE_URL=str(store_root),
        OMNIDATA_DATA_DIR=str(data_dir), OMNIDATA_LEASE_S="30", OMNIDATA_RENDER_DEVICE="cpu",
        **extra,
    )
    return env


def wait_until(cond: Any, timeout: float, what: str, proc: subprocess.Popen[bytes] | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"worker exited with {proc.returncode} while waiting for {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def stop_worker(proc: subprocess.Popen[bytes]) -> None:
    """Warm shutdown as an orchestrator does it (k8s, docker stop): SIGTERM to the main process only, which
    then stops its pool. Signalling the whole group kills the children outright (Celery resets their SIGTERM
    to the default) and races billiard's pool shutdown. The group is killed only if that hangs."""
    os.kill(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


@pytest.mark.slow
def test_real_worker_consumes_heartbeats_and_recycles_its_child(pg_url, pg_sm, redis_url, banana, tmp_path):  # noqa: F811
    from services.scheduler.celery_transport import CeleryTransport

    # one task per message (no view batch), so that two messages are two tasks and recycle the child
    tmpdir = tmp_path / "tmp"  # its own: what the worker's children leave in the temp dir shows
    tmpdir.mkdir()
    env = worker_env(pg_url, redis_url, banana.store.root, tmp_path / "data", OMNIDATA_WORKER_MAX_TASKS="2",
                     OMNIDATA_WORKER_BATCH_VIEWS="false", TMPDIR=str(tmpdir))
    log = (tmp_path / "worker.log").open("wb")
    name = f"w-{secrets.token_hex(3)}@%h"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "worker", "--concurrency", "1",
                             "--render-threads", "1", "--hostname", name], cwd=REPO, env=env, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    try:
        def workers() -> list[Worker]:
            with pg_sm() as s:
                return [w for w in s.scalars(select(Worker)).all() if w.queues == ["render", "derive"]]

        before = {w.id for w in workers()}
        wait_until(lambda: {w.id for w in workers()} - before, 60, "the first heartbeat", proc)
        run_started = {w.id: w.started_at for w in workers() if w.id not in before}
        job_id = make_job(pg_sm, banana)
        ids = [queue(pg_sm, job_id, c, 0, v) for c in ("passes", "point_info") for v in (0, 1)]
        with pg_sm() as s:
            cues = dict(s.execute(select(Task.id, Task.cue).where(Task.id.in_(ids))).all())
        transport = CeleryTransport(settings=get_settings(broker_url=redis_url))
        transport.send([(i, cues[i]) for i in ids])
        transport.close()

        def states() -> set[str]:
            with pg_sm() as s:
                return set(s.scalars(select(Task.state).where(Task.id.in_(ids))))

        wait_until(lambda: states() == {"done"}, 180, "the tasks to finish", proc)
        with pg_sm() as s:
            ran_by = set(s.scalars(select(Task.worker_id).where(Task.id.in_(ids))))
        # worker_max_tasks=2: the child process was replaced after two tasks, and both ran under the given
        # name
        assert ran_by == {name.replace("%h", socket.gethostname())}, ran_by
        assert ran_by == {w.id for w in workers()} - before  # one row, kept across the recycle

        def counted() -> int:
            return sum(w.tasks_done for w in workers() if w.id in ran_by)

        wait_until(lambda: counted() == 4, 30, "heartbeats to count the tasks of both children", proc)
        # a recycled child is the same run of the worker (a restart is a new one, which the scheduler notes)
        assert {w.id: w.started_at for w in workers() if w.id in ran_by} == run_started
        assert b"Celery recycles it" in (tmp_path / "worker.log").read_bytes()
    finally:
        stop_worker(proc)
        log.close()
    assert proc.returncode == 0, (tmp_path / "worker.log").read_text()[-3000:]
    # both children rendered (bpy made a session folder in TMPDIR each) and left through os._exit: none is
    # left
    assert not list(tmpdir.glob("blender_*"))


@pytest.mark.slow
def test_a_worker_restarted_under_its_name_is_a_new_run(pg_url, pg_sm, redis_url, banana, tmp_path):  # noqa: F811
    """A container restarted in place keeps its name (hostname and pid): its row's start moves on, before it
    consumes, which the scheduler reads as the death of the run before (services.scheduler.resend)."""
    env = worker_env(pg_url, redis_url, banana.store.root, tmp_path / "data")
    name = f"w-{secrets.token_hex(3)}@%h"
    worker_id = name.replace("%h", socket.gethostname())

    def start(log: str) -> subprocess.Popen[bytes]:
        with (tmp_path / log).open("wb") as out:
            cmd = [sys.executable, "-m", "services.cli", "worker", "--concurrency", "1", "--hostname", name]
            return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True)

    def run_start() -> Any:
        with pg_sm() as s:
            row = s.get(Worker, worker_id)
            return row.started_at if row is not None else None

    first = start("first.log")
    try:
        wait_until(lambda: run_start() is not None, 60, "the first run's row", first)
        first_start = run_start()
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait()
    second = start("second.log")
    try:
        wait_until(lambda: run_start() > first_start, 60, "the second run's row", second)
    finally:
        os.killpg(second.pid, signal.SIGKILL)
        second.wait()


def tree_cpu_s(root_pid: int) -> float:
    """CPU seconds (user + system, from /proc) used so far by a process and all its descendants alive now."""
    tick = os.sysconf("SC_CLK_TCK")
    stats: dict[int, tuple[int, float]] = {}  # pid -> (parent pid, cpu seconds)
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # exited meanwhile
            continue
        stats[int(entry.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / tick)
    tree, grown = {root_pid}, True
    while grown:
        children = {pid for pid, (ppid, _) in stats.items() if ppid in tree} - tree
        grown = bool(children)
        tree |= children
    return sum(stats[pid][1] for pid in tree if pid in stats)


@pytest.mark.slow
def test_idle_worker_with_one_render_thread_does_not_spin(pg_url, pg_sm, redis_url, banana, tmp_path):  # noqa: F811
    """After a render, a worker started with --render-threads 1 sleeps: its process tree uses < 5% of a
    core."""
    from services.scheduler.celery_transport import CeleryTransport

    env = worker_env(pg_url, redis_url, banana.store.root, tmp_path / "data")
    log = (tmp_path / "worker.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "worker", "--concurrency", "1", "--render-threads", "1"],
        cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )
    try:
        job_id = make_job(pg_sm, banana)
        tid = queue(pg_sm, job_id, "passes", 0, 0)
        transport = CeleryTransport(settings=get_settings(broker_url=redis_url))
        transport.send([(tid, "passes")])
        transport.close()

        def state() -> str | None:
            with pg_sm() as s:
                return s.scalar(select(Task.state).where(Task.id == tid))

        wait_until(lambda: state() == "done", 180, "the render task", proc)
        time.sleep(2.0)  # let the task's bookkeeping (ack, heartbeat) settle
        cpu0, t0 = tree_cpu_s(proc.pid), time.monotonic()
        time.sleep(10.0)
        idle = (tree_cpu_s(proc.pid) - cpu0) / (time.monotonic() - t0)
        assert idle < 0.05, f"idle worker used {idle:.0%} of a core"
    finally:
        stop_worker(proc)
        log.close()


def test_worker_engine_commits_without_waiting_for_the_wal_flush_on_postgres(pg_url, tmp_path):
    from sqlalchemy import text

    engine = tasks.worker_engine(pg_url)
    try:
        with engine.connect() as c:
            assert c.execute(text("SHOW synchronous_commit")).scalar() == "off"
    finally:
        engine.dispose()
    # SQLite has no such option: engine as usual
    sqlite = tasks.worker_engine(f"sqlite:///{tmp_path / 'w.db'}")
    with sqlite.connect() as c:
        assert c.execute(text("SELECT 1")).scalar() == 1
    sqlite.dispose()
