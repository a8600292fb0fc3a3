"""The worker's Celery app: the shared broker configuration plus worker-only options, kept apart from the
scheduler's so sending a task never imports the worker.

Postgres is the source of truth; Redis only carries `render.cue(task_id)` messages. Messages are acked after
the task ran (acks_late) and given back when the worker process dies (reject_on_worker_lost), one at a time
(prefetch 1); a lost message is harmless because the scheduler's reaper re-queues tasks that stay queued
too long. Child processes recycle after `worker_max_tasks` messages or above `worker_max_memory_mb`.

`celery -A services.worker.celery_app worker` also works: the module exposes `app` lazily.
"""

from __future__ import annotations

from celery import Celery

from services.core.celery_config import celery_conf
from services.core.settings import Settings, get_settings
from services.worker.process.numeric_threads import pin_numeric_threads

# `celery -A` starts here, before the task modules load numpy (`omnidata worker` did it already)
pin_numeric_threads()

TASK_MODULES = ("services.worker.tasks",)


def worker_conf(settings: Settings) -> dict[str, object]:
    """Celery configuration of a worker: the shared one (acks_late, prefetch, child recycling: celery_conf)
    plus the options only a consuming worker reads."""
    conf = celery_conf(settings)
    conf.update(
        {
            "task_reject_on_worker_lost": True,  # a killed child's message goes back to the queue
            # failures are recorded in Postgres; never loop a message
            "task_acks_on_failure_or_timeout": True,
            "broker_connection_retry": True,
            "broker_connection_max_retries": None,  # a restarted Redis is waited for, however long it takes
            "broker_channel_error_retry": True,
            "worker_cancel_long_running_tasks_on_connection_loss": False,  # the lease protects them instead
            "worker_send_task_events": False,
            "worker_proc_alive_timeout": 60.0,  # child start imports numpy/sqlalchemy; slow disks need time
        }
    )
    return conf


def create_app(settings: Settings | None = None) -> Celery:
    """A Celery app for a render worker, with `render.cue` registered."""
    settings = settings or get_settings()
    app = Celery("omnidata-worker", set_as_current=True, include=list(TASK_MODULES))
    app.conf.update(worker_conf(settings))
    app.conf["omnidata_settings"] = settings  # read by the task runtime in each child process
    import services.worker.tasks  # noqa: F401  (registers the shared task on this app)

    return app


_app: Celery | None = None


def __getattr__(name: str) -> Celery:
    # `celery -A services.worker.celery_app` looks up `app`/`celery`: build it from the environment on demand,
    # so importing this module has no side effect.
    global _app
    if name in ("app", "celery"):
        if _app is None:
            _app = create_app()
        return _app
    raise AttributeError(name)
