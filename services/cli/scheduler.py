"""`omnidata scheduler [--once] [--interval S]`: the scheduler process, configured by OMNIDATA_* variables."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from services.cli import CliError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata scheduler`."""
    parser.add_argument(
        "--once", action="store_true", help="run one tick (plan, reap, dispatch, complete) and exit"
    )
    parser.add_argument("--interval", type=float, default=1.0, metavar="S",
                        help="seconds between ticks when idle (default 1)")
    parser.add_argument("--id", dest="scheduler_id", default=None, help="scheduler id (default host:pid)")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def run(args: argparse.Namespace) -> int:
    """Start the scheduler; returns the exit status (0 on a clean stop by SIGTERM/SIGINT)."""
    from services.core.db.engine import make_engine, make_sessionmaker, migrate, require_schema
    from services.core.settings import load_settings
    from services.core.storage import open_store
    from services.scheduler.celery_transport import CeleryTransport
    from services.scheduler.loop import Scheduler

    if args.interval <= 0:
        raise CliError(f"--interval must be positive, got {args.interval}")
    settings = load_settings()
    if settings.is_sqlite:
        migrate(settings.database_url)  # embedded: nobody else runs the migrations
    # before logging is set up: a refusal is one line, not Alembic's chatter
    require_schema(settings.database_url, settings.db_wait_s)
    logging.basicConfig(
        level=getattr(logging, args.log_level), stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    engine = make_engine(settings.database_url)
    store = open_store(settings.storage_url, settings)
    transport = CeleryTransport(settings=settings)
    # The service loop plans in capped child processes; a single --once tick plans inline (it waits for it
    # anyway).
    sched = Scheduler(make_sessionmaker(engine), store, transport, settings, args.scheduler_id,
                      plan_in_processes=not args.once, cap_queue=True)
    try:
        if args.once:
            res = sched.tick()
            logging.getLogger(__name__).info(
                "tick: planned %s, dispatched %d, finished %s", res.planned, res.dispatched.sent,
                [f.job_id for f in res.finished],
            )
            return 0
        stop = threading.Event()

        def _stop(signum: int, _frame: object) -> None:
            logging.getLogger(__name__).info("signal %d: stopping after this tick", signum)
            stop.set()

        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
        sched.run_forever(stop, interval=args.interval)
        return 0
    finally:
        transport.close()
        engine.dispose()
