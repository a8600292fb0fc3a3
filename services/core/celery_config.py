"""Celery wiring shared by the scheduler (sends tasks by name) and the worker (consumes them).

Only names, queues and broker options live here, so the scheduler and API can build a bare Celery app
that never imports the worker (and so never bpy): tasks are sent with
`app.send_task(TASK_RENDER_CUE, args=[task_id], queue=queue_for_cue(cue, settings))`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from services.core.settings import Settings

if TYPE_CHECKING:  # the names and queues below are read where Celery never runs (an embedded generate)
    from celery import Celery

TASK_RENDER_CUE = "render.cue"  # args=[task_id]; the worker loads everything else from the database
RENDER_CUES: frozenset[str] = frozenset({"passes"})  # cues that run Cycles; all others are light derivations
# A message not acked within this time is redelivered by Redis; duplicates are harmless (the worker's
# claim needs state 'queued'), so it only has to exceed the longest render by a wide margin.
MIN_VISIBILITY_TIMEOUT_S = 3600


def queue_for_cue(cue: str, settings: Settings) -> str:
    """Queue of a task: the render queue for Cycles passes, the derive queue for everything else."""
    return settings.queue_render if cue in RENDER_CUES else settings.queue_derive


def celery_conf(settings: Settings) -> dict[str, object]:
    """Celery configuration for both sides: JSON only, acks_late, prefetch 1, no result backend."""
    return {
        "broker_url": settings.broker_url,
        "broker_connection_retry_on_startup": True,
        "broker_transport_options": {
            "visibility_timeout": max(MIN_VISIBILITY_TIMEOUT_S, 4 * settings.lease_s),
            "socket_timeout": 30,
            "socket_connect_timeout": 10,
            "retry_on_timeout": False,  # kombu's pipelined batch publish refuses auto-retrying clients
        },
        "task_serializer": "json",
        "accept_content": ["json"],
        "result_backend": None,
        "task_ignore_result": True,  # results live in Postgres, not in the broker
        "task_acks_late": True,  # a worker killed mid-task leaves the message to be redelivered
        # long tasks: never hoard messages another worker could run (a dead worker's reserved ones are
        # re-sent)
        "worker_prefetch_multiplier": settings.worker_prefetch,
        "task_default_queue": settings.queue_derive,
        "task_create_missing_queues": True,
        "task_routes": {TASK_RENDER_CUE: {"queue": settings.queue_derive}},  # overridden per send by cue
        "worker_max_tasks_per_child": settings.worker_max_tasks,
        "worker_max_memory_per_child": settings.worker_max_memory_mb * 1024,  # KiB
        "worker_hijack_root_logger": False,
        "broker_pool_limit": 4,
    }


def make_celery_app(settings: Settings, main: str = "omnidata") -> Celery:
    """A Celery app configured from settings, with no tasks registered (senders use send_task by name)."""
    from celery import Celery

    app = Celery(main, set_as_current=False)
    app.conf.update(celery_conf(settings))
    return app
