"""`omnidata worker [--queues render,derive] [--concurrency N] [--loglevel L]`: a Celery render worker.

Configured by OMNIDATA_* variables (database, broker, storage); several workers on several machines share the
work. Each child process runs one task at a time (prefetch 1, acks late) and recycles itself after
OMNIDATA_WORKER_MAX_TASKS tasks or above OMNIDATA_WORKER_MAX_MEMORY_MB.
"""

from __future__ import annotations

import argparse
import os
import socket
from typing import TYPE_CHECKING

from services.cli import CliError

if TYPE_CHECKING:
    from services.core.settings import Settings

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
WORKER_NAME_HELD_S = 30.0  # a heartbeat this recent means the name is in use (beats come every 5 s)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata worker`."""
    parser.add_argument("--queues", "-Q", default=None,
                        help="comma-separated queues to consume (default: the render and derive queues)")
    parser.add_argument("--concurrency", "-c", type=int, default=None,
                        help="worker processes (default: one per core this process may use, so renders and "
                             "derivations use every core; each renders with cores / processes threads)")
    parser.add_argument("--loglevel", "-l", default="INFO", type=str.upper, choices=LOG_LEVELS)
    parser.add_argument(
        "--hostname", "-n", default=None, help="Celery node name (default omnidata-<pid>@<host>)"
    )
    parser.add_argument("--render-threads", type=int, default=None,
                        help="Cycles CPU threads per process (default: the process's CPU affinity)")
    parser.add_argument("--pool", default="prefork", choices=["prefork", "solo", "threads"],
                        help="Celery pool (default prefork: crashes and leaks stay in a child process)")


def node_name(hostname: str | None) -> str:
    """The Celery node name: `--hostname` with Celery's %h/%n/%d expanded, default omnidata-<pid>@<host>.

    It is also the worker's id in /workers (a child process of a --concurrency N worker adds -1 ... -(N-1)).
    """
    from celery.utils.nodenames import default_nodename, host_format

    return host_format(default_nodename(hostname or f"omnidata-{os.getpid()}@{socket.gethostname()}"))


def process_layout(concurrency: int | None, render_threads: int | None, cores: int) -> tuple[int, int]:
    """(worker processes, render threads per process) on `cores` cores: by default one process per core with
    one thread each, as `omnidata generate` does (a view's derivations run on one core, so a single process
    with many render threads would leave the other cores idle between renders); CliError for values below
    1."""
    if concurrency is not None and concurrency < 1:
        raise CliError(f"--concurrency must be at least 1, got {concurrency}")
    if render_threads is not None and render_threads < 1:
        raise CliError(f"--render-threads must be at least 1, got {render_threads}")
    processes = concurrency or cores
    return processes, render_threads or max(1, cores // processes)


def worker_argv(args: argparse.Namespace, queues: list[str]) -> list[str]:
    """The argv given to Celery's `worker` command."""
    node = node_name(args.hostname)
    return [
        "worker",
        f"--queues={','.join(queues)}",
        f"--concurrency={args.concurrency}",
        f"--loglevel={args.loglevel}",
        f"--hostname={node}",
        f"--pool={args.pool}",
        "--without-gossip",  # no worker-to-worker chatter: the database knows who is alive (heartbeats)
        "--without-mingle",
        "--without-heartbeat",
    ]


def _live_holder(settings: Settings, node: str) -> str | None:
    from services.core.db.engine import make_engine, make_sessionmaker, wait_for_database
    from services.worker.run.heartbeat import live_holder

    def holder() -> str | None:
        engine = make_engine(settings.database_url)
        try:
            return live_holder(make_sessionmaker(engine), node, within_s=WORKER_NAME_HELD_S)
        finally:
            engine.dispose()

    return wait_for_database(holder, settings.db_wait_s)


def run(args: argparse.Namespace) -> int:
    """Start the worker; returns when Celery stops (SIGTERM: warm shutdown after the current task)."""
    from services.core.db.engine import require_schema
    from services.core.settings import load_settings
    from services.embedded.pool import cpu_count
    from services.worker.celery_app import create_app
    from services.worker.process.numeric_threads import pin_numeric_threads

    env_threads = os.environ.get("OMNIDATA_RENDER_THREADS", "")
    wanted = args.render_threads or (int(env_threads) if env_threads.isdigit() else None)
    args.concurrency, threads = process_layout(args.concurrency, wanted, cpu_count())
    os.environ["OMNIDATA_RENDER_THREADS"] = str(threads)  # Settings.render_threads of each child
    pin_numeric_threads()  # for the children too (numpy is not loaded yet in this process)
    settings = load_settings()
    require_schema(settings.database_url, settings.db_wait_s)
    node = node_name(args.hostname)
    holder = _live_holder(settings, node)
    if holder is not None:
        raise CliError(f"a worker named {node!r} is alive on {holder}: give this one another --hostname")
    queues = [
        q.strip() for q in (args.queues or f"{settings.queue_render},{settings.queue_derive}").split(",")
    ]
    queues = [q for q in queues if q]
    if not queues:
        raise CliError("--queues names no queue")
    app = create_app(settings)
    app.conf["omnidata_queues"] = queues
    app.conf["omnidata_worker_name"] = node  # the children's worker id
    app.worker_main(worker_argv(args, queues))
    return 0
