"""Celery tasks of the worker: thin wrappers that validate the payload, call the TaskRunner and map transient
errors to retries (so the logic is testable without Celery). Everything else (state, results, errors)
lives in the database.

Each worker child process builds its own runtime (database engine, object store, TaskRunner, heartbeat thread)
after the fork: connections and threads must not cross a fork. The main process writes the worker's row once,
before it consumes, as the messages it reserves are the worker's from then on.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from celery import Celery, shared_task
from celery import Task as CeleryTask
from celery.signals import worker_init, worker_process_init, worker_process_shutdown

from services.core.celery_config import TASK_RENDER_CUE
from services.core.settings import Settings, get_settings

if TYPE_CHECKING:  # imported lazily at run time: the Celery app imports this module and must stay light
    from collections.abc import Callable

    from sqlalchemy import Engine
    from sqlalchemy.orm import Session

    from services.worker.run.heartbeat import Heartbeat
    from services.worker.run.runner import TaskRunner

log = logging.getLogger(__name__)

MAX_TRANSIENT_RETRIES = 20  # broker-level retries of a task whose claim could not reach the database
RETRY_CAP_S = 30.0
# A worker's S3 request tries this often through 5xx (up to ~7 s of backoff, not a minute): past that its job
# is held for the store (TaskLedger.hold_for_storage), which says so at once and retries it for as long as it
# takes.
WORKER_S3_ATTEMPTS = 4


@dataclass
class Runtime:
    """What one worker process holds: settings, engine, store, runner and heartbeat."""

    pid: int
    settings: Settings
    engine: Engine
    runner: TaskRunner
    heartbeat: Heartbeat

    def close(self) -> None:
        """Stop the heartbeat, free the space and close database connections."""
        try:
            self.heartbeat.stop()
        finally:
            self.runner.close()
            self.engine.dispose()


_runtime: Runtime | None = None
_lock = threading.Lock()


def _settings_from_app(app: Celery | None) -> Settings:
    s = app.conf.get("omnidata_settings") if app is not None else None
    return s if isinstance(s, Settings) else get_settings()


def worker_engine(database_url: str, **kwargs: Any) -> Engine:
    """The worker's database engine; on Postgres its commits do not wait for the WAL flush (synchronous_commit
    off).

    Every claim and result of the whole fleet updates the same few counter rows of a job, and a commit that
    holds their row locks through an fsync serialises the workers (bench/scale/scale_sim.py: at 1,000 workers
    backends wait on those locks and claims take seconds). A server crash can lose the last fraction of a
    second of worker commits, which tasks survive by design: a lost claim leaves a queued task the reaper
    sends again, a lost result a running task whose lease runs out and whose rerun writes identical bytes.
    """
    from sqlalchemy.engine import make_url

    from services.core.db.engine import make_engine

    if make_url(database_url).get_backend_name() == "postgresql":
        kwargs.setdefault("connect_args", {"options": "-c synchronous_commit=off"})
        # No SELECT 1 before every checkout: a claim or result is one statement, and a ping doubled its round
        # trips. A connection that died meanwhile (Postgres restarted) fails its statement instead, which the
        # runner retries (TaskRunner._db) on a fresh one and the heartbeat retries on its next beat.
        kwargs.setdefault("pool_pre_ping", False)
    return make_engine(database_url, **kwargs)


def build_runtime(settings: Settings, *, queues: list[str] | None = None, name: str | None = None) -> Runtime:
    """Engine, store, TaskRunner and a started heartbeat for this process (worker id: see
    default_worker_id)."""
    from services.core.db.engine import make_sessionmaker
    from services.core.storage import open_store
    from services.worker.process.heap import keep_freed_memory
    from services.worker.run.heartbeat import expire_leases
    from services.worker.run.runner import TaskRunner, default_worker_id

    keep_freed_memory()  # the process that runs tasks reuses the pages it frees (prefork child or solo)
    engine = worker_engine(settings.database_url)
    sessions = make_sessionmaker(engine)
    store = open_store(settings.storage_url, settings, s3_attempts=WORKER_S3_ATTEMPTS)
    worker_id = default_worker_id(name)
    if name:
        # One process holds a named id at a time: a task still running under it was left by the child this
        # process replaces (killed mid-task). End its lease so the reaper retries it now, not minutes later.
        expire_leases(sessions, [worker_id])
    hb = worker_heartbeat(sessions, worker_id, settings, queues)
    runner = TaskRunner(sessions, store, settings, worker_id, heartbeat=hb)
    hb.start()
    return Runtime(os.getpid(), settings, engine, runner, hb)


def worker_heartbeat(sessions: Callable[[], Session], worker_id: str, settings: Settings,
                     queues: list[str] | None) -> Heartbeat:
    """The heartbeat of a Celery worker's process, beating often enough for the reaper's heartbeat timeout."""
    from services.worker.run.heartbeat import Heartbeat, heartbeat_interval

    return Heartbeat(sessions, worker_id, queues=queues or [settings.queue_render, settings.queue_derive],
                     lease_s=settings.lease_s,
                     interval_s=heartbeat_interval(min(settings.lease_s, settings.heartbeat_timeout_s)))


def get_runtime(app: Celery | None = None) -> Runtime:
    """This process's runtime, built on first use (and again after a fork)."""
    global _runtime
    with _lock:
        if _runtime is None or _runtime.pid != os.getpid():
            settings = _settings_from_app(app)
            queues = app.conf.get("omnidata_queues") if app is not None else None
            name = app.conf.get("omnidata_worker_name") if app is not None else None
            _runtime = build_runtime(settings, queues=queues, name=name)
        return _runtime


@worker_init.connect
def _load_kernel_target(**_: object) -> None:
    # In the worker's main process, before its pool forks: every child, recycled ones too, inherits numba's
    # target instead of making it in its first view (kernel_target.load).
    from services.worker.process import kernel_target

    try:
        kernel_target.load()
    except Exception:  # each child makes it at its first kernel instead
        log.exception("numba's target could not be made ahead of the pool")


@worker_init.connect
def _write_worker_row(sender: Any = None, **_: object) -> None:
    # In the main process, before it consumes: its prefetch reserves messages before the pool's children make
    # their first beat, and a worker killed then must have a row for the scheduler to declare dead and send
    # those messages again (services.scheduler.resend), instead of waiting for the lost-message timeout. The
    # row's start moves to now: a run of this name that died before this one counts as dead there too.
    from services.core.db.engine import make_sessionmaker

    app: Celery | None = getattr(sender, "app", None)
    name = app.conf.get("omnidata_worker_name") if app is not None else None
    if app is None or not name:  # an unnamed worker's children are host:pid: no id to write for them here
        return
    settings = _settings_from_app(app)
    engine = worker_engine(settings.database_url)
    try:
        queues = app.conf.get("omnidata_queues")
        worker_heartbeat(make_sessionmaker(engine), name, settings, queues).register()
    except Exception:  # the children beat as usual; only a kill before their first beat is recovered later
        log.exception("the worker row could not be written before consuming")
    finally:
        engine.dispose()


@worker_process_init.connect
def _init_child(**_: object) -> None:
    # A fresh child: forget the parent's runtime (its threads did not survive the fork) and start beating
    # right away, so the dashboard sees idle workers too. Building it is quick: bpy loads on the first render.
    global _runtime
    _runtime = None
    try:
        from celery import current_app

        get_runtime(current_app)
    except Exception:  # the first task will try again and report the error properly
        log.exception("worker runtime could not start; will retry on the first task")


@worker_process_shutdown.connect
def _shutdown_child(**_: object) -> None:
    global _runtime
    if _runtime is not None and _runtime.pid == os.getpid():
        try:
            _runtime.close()
        except Exception:
            log.exception("closing the worker runtime failed")
        _runtime = None
    from services.worker.blender.threads import remove_session_temp_dir

    remove_session_temp_dir()  # a prefork child leaves through os._exit, past Blender's own removal


def guard_renders_from_sigterm() -> None:
    """In a prefork child, billiard's SIGTERM handler (installed after worker_process_init, hence here) raises
    SystemExit; raised inside a render it would exit through Blender's C++ teardown and hang
    (services.worker.blender.calls), so there the child ends at once instead. Another pool's handler stays as
    it is: the solo pool's warm shutdown lets the running task finish."""
    from billiard.common import _shutdown_cleanup  # the child's handler (billiard.pool.Worker.after_fork)

    from services.worker.blender.calls import exit_at_once_inside_blender

    if signal.getsignal(signal.SIGTERM) is _shutdown_cleanup:
        exit_at_once_inside_blender(signal.SIGTERM)


def _task_id(payload: object) -> int | None:
    if isinstance(payload, bool):
        return None
    if isinstance(payload, int):
        return payload if payload > 0 else None
    if isinstance(payload, str) and payload.isdigit():
        return int(payload) or None
    return None


@shared_task(name=TASK_RENDER_CUE, bind=True, acks_late=True, reject_on_worker_lost=True, ignore_result=True,
             max_retries=MAX_TRANSIENT_RETRIES)
def render_cue(self: CeleryTask, task_id: object) -> str:
    """Run one point-view-cue task by id; returns the outcome status (done, skipped, retry, failed, ...)."""
    from services.worker.run.claim import TransientError

    tid = _task_id(task_id)
    if tid is None:  # a malformed message can never succeed: drop it (acked), do not retry
        log.error("render.cue: invalid task id %r; message dropped", task_id)
        return "invalid"
    guard_renders_from_sigterm()
    try:
        outcome = get_runtime(self.app).runner.run(tid)
    except TransientError as exc:
        countdown = min(RETRY_CAP_S, 2.0 ** self.request.retries)
        log.warning("render.cue(%d): %s; retrying in %.0f s", tid, exc, countdown)
        raise self.retry(exc=exc, countdown=countdown) from None
    log.info("render.cue(%d) %s: %s in %.2f s%s", tid, outcome.cue, outcome.status, outcome.duration_s,
             f" ({outcome.error.splitlines()[0]})" if outcome.error and outcome.status != "skipped" else "")
    if outcome.batch:
        log.info("render.cue(%d): with its view batch of %d more tasks: %s", tid, len(outcome.batch),
                 ", ".join(f"{o.cue} {o.status}" for o in outcome.batch))
    if outcome.recycle:
        # worker_max_tasks_per_child / worker_max_memory_per_child recycle the child after this task.
        log.info("worker process %d reached its memory or task limit; Celery recycles it", os.getpid())
    return outcome.status
