"""Orchestration CPU per task, step by step, without the simulation's contention (issue 23's ">= 2,000 tasks/s
on one orchestrator core").

One process drives the real parts in turn against a fresh Postgres database and a private redis-server:
the Scheduler's dispatch pass (real CeleryTransport into Redis), then one worker's TaskRunner running every
dispatched task (claim + record done; its compute step stores a few bytes), heartbeats, the reaper's pass and
the progress query. Each part has its own connection (application_name), so the CPU of the Postgres backend
serving it is read from /proc, besides this process's own CPU while the scheduler code runs and Redis' CPU.

Compaction (on by default in the product): after each round's tasks ran, the scheduler's Compactor packs the
views that round finished (`compact_after_s` 0 here, so every finished view is packed once, as the scheduler
would a minute later), on its own connection; its Python and its backend's CPU count as the scheduler's, per
task (`compaction_py`, `pg_compaction`). Before it, a walker that finds nothing due reads the round's done
rows (and a chunk of pending ones): the CPU per row a pass spends walking views finished less than
`compact_after_s` ago; in steady state a pass a second walks `--rate` x compact_after_s such rows (at most
compact_pass_s of it), which is `compaction_walk` per task (a walk that stops at the first chunk not due: its
measured chunks a pass). `--no-compaction` leaves it all out (the figures before compaction existed).

Per task, orchestration = scheduler (Python) + its Postgres backend + Redis + the worker's claim/record
backend + compaction (Python + backend) + heartbeats and reaper passes scaled to a fleet (`--workers` beating
every 5 s, a reaper pass every 5 s, at `--rate` tasks/s). The worker's own Python is not orchestration (it
scales with the workers).

Writes bench/results/orchestration_cpu.json under `orchestration_cpu[--label]` (`--key` for another key).
Run: .venv/bin/python bench/scale/orchestration_cpu.py [--views 4000] [--rounds 6] [--label NAME]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from sqlalchemy import text

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.scale_cost import ROOM_CUES, PrivateRedis, cpu_seconds, with_app_name  # noqa: E402
from bench.lib.scale_procs import SleepingRunner, task_id_of  # noqa: E402
from bench.scale.fanout import (  # noqa: E402
    create_database,
    drop_database,
    labelled_space,
    percentiles,
    plan_is,
    synthetic_plan,
)
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.jobs import create_job  # noqa: E402
from services.core.db.models import Space  # noqa: E402
from services.core.domain.jobspec import JobSpec  # noqa: E402
from services.core.settings import get_settings  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.worker.run.heartbeat import HEARTBEAT_INTERVAL_S, Heartbeat  # noqa: E402
from services.worker.tasks import worker_engine  # noqa: E402

RESULTS = results_dir()


def _backend(sm: Any) -> int:
    with sm() as s:
        return int(s.scalar(text("SELECT pg_backend_pid()")) or 0)


class Part:
    """A part of the system with its own connection: its sessionmaker and its backend's pid."""

    def __init__(self, url: str, name: str, worker: bool = False) -> None:
        url = with_app_name(url, name)
        self.engine = (
            worker_engine(url, pool_size=1) if worker else make_engine(url, pool_size=1, max_overflow=0)
        )
        self.sm = make_sessionmaker(self.engine)
        self.pid = _backend(self.sm)

    def cpu(self) -> float:
        """CPU seconds of its backend so far."""
        return cpu_seconds(self.pid)


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Plan a job, then `rounds` x (dispatch pass, run what it sent); CPU per part and per task."""
    import redis

    from services.api.jobs.service import fetch_job_detail
    from services.scheduler.celery_transport import CeleryTransport
    from services.scheduler.compaction import Compactor
    from services.scheduler.loop import Scheduler
    from services.scheduler.reaper import reap_once

    red = PrivateRedis()
    url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="omnidata-orch-cpu-"))
    try:
        migrate(url)
        settings = get_settings(
            data_dir=tmp, database_url=url, broker_url=red.url, storage_url=f"file://{tmp}/o",
            dispatch_window=args.window, lease_s=300,
        )
        if args.no_view_batches and "worker_batch_views" in type(settings).model_fields:
            settings = settings.model_copy(update={"worker_batch_views": False})
        sched_part, worker_part, api_part = (
            Part(url, "scheduler"), Part(url, "workers", worker=True), Part(url, "api"),
        )
        compact_part = Part(url, "compaction")
        # every finished view is due at once (the scheduler waits compact_after_s, then packs each view once);
        # a pass as long as it takes, so each round's views are packed in that round
        compactor = (None if args.no_compaction else
                     Compactor(compact_part.sm, after_s=0.0, pass_s=3600.0))
        # the product compacts a view compact_after_s after it finished, so each pass also walks the views
        # finished since (done, not due yet): a walker that finds none due measures that walk's CPU per row
        # read
        walker = None if args.no_compaction else Compactor(compact_part.sm, after_s=1e9, pass_s=3600.0)
        walk = {"cpu_s": 0.0, "chunks": 0, "passes": 0, "done_rows": 0}
        if walker is not None:
            walk_chunk = walker.compact_chunk

            def counted_chunk(*a: Any, **k: Any) -> Any:
                walk["chunks"] += 1
                return walk_chunk(*a, **k)

            walker.compact_chunk = counted_chunk  # type: ignore[method-assign]
        store = LocalStore(tmp / "o")
        space_id = labelled_space(sched_part.sm, store, "orch")
        with sched_part.sm() as s:
            job = create_job(
                s, owner="bench", spec=JobSpec(cues=ROOM_CUES, name="orch"), spaces=[s.get(Space, space_id)]
            )
            s.commit()
            job_id = job.id
        plan = synthetic_plan("orch", args.views // 4, 4, resolution=32)
        transport = CeleryTransport(settings=settings, **({"prebuilt": False} if args.kombu else {}))
        # (a tree before prebuilt messages has kombu's only)
        prebuilt = hasattr(transport, "_push") and not args.kombu
        plan_is(plan)
        sched = Scheduler(sched_part.sm, store, transport, settings, "orch", cache_dir=tmp / "cache",
                          budget=args.window)
        sched.plan_pending()
        runner = SleepingRunner(
            worker_part.sm, store, settings, "orch-worker", task_s=1e-6, killed=threading.Event()
        )
        beat = Heartbeat(worker_part.sm, "orch-worker", queues=["render", "derive"], lease_s=300)
        r = redis.Redis.from_url(red.url)
        queues = [settings.queue_render, settings.queue_derive]
        # warm-up: a pass and its tasks (caches loaded, statements prepared)
        totals = {"sched_py": 0.0, "pg_sched": 0.0, "redis": 0.0, "pg_worker": 0.0, "compaction_py": 0.0,
                  "pg_compaction": 0.0, "tasks": 0, "sent": 0, "views_compacted": 0, "tasks_compacted": 0}
        passes_ms: list[float] = []
        for rnd in range(args.rounds + 1):
            c0, p0, rd0 = time.process_time(), sched_part.cpu(), cpu_seconds(red.pid)
            t = time.perf_counter()
            res = sched.dispatch_once()
            passes_ms.append(time.perf_counter() - t)
            c1, p1 = time.process_time(), sched_part.cpu()
            w0 = worker_part.cpu()
            n = 0
            # run what is queued, but leave `--leave` of it in flight for the next pass (a fleet never drains
            # the window): the next pass then scans past tasks whose inputs are still queued or running
            todo = int(sum(r.llen(q) for q in queues) * (1 - args.leave)) if rnd < args.rounds else 10**9
            popped = 0
            while popped < todo and (got := r.rpop(queues[0]) or r.rpop(queues[1])) is not None:
                popped += 1
                out = runner.run(task_id_of(got))  # with view batches: the view's other tasks too, their
                assert out.status in ("done", "skipped"), out  # messages then skipped
                n += sum(o.status == "done" for o in (out, *getattr(out, "batch", ())))
            rd1, w1 = cpu_seconds(red.pid), worker_part.cpu()
            if walker is not None and rnd > 0:
                k0, kp0 = time.process_time(), compact_part.cpu()
                # walks this round's done rows (or stops at the first not due); packs nothing
                walker.run_once()
                walk["cpu_s"] += time.process_time() - k0 + compact_part.cpu() - kp0
                walk["passes"] += 1
                walk["done_rows"] += n
            k0, kp0 = time.process_time(), compact_part.cpu()
            packed = compactor.run_once() if compactor is not None else None
            k1, kp1 = time.process_time(), compact_part.cpu()
            if rnd == 0:
                continue
            totals["compaction_py"] += k1 - k0
            totals["pg_compaction"] += kp1 - kp0
            if packed is not None:
                totals["views_compacted"] += packed.views
                totals["tasks_compacted"] += packed.tasks
            totals["sched_py"] += c1 - c0
            totals["pg_sched"] += p1 - p0
            totals["redis"] += rd1 - rd0
            totals["pg_worker"] += w1 - w0
            totals["tasks"] += n
            totals["sent"] += res.sent
        tasks = max(int(totals["tasks"]), 1)
        # a heartbeat, a reaper pass and a progress query: CPU each (this process + its backend)
        beat_ms = _cpu_ms(lambda: beat.beat(), worker_part, 200)
        reap_ms = _cpu_ms(lambda: _reap(sched_part.sm, reap_once, settings), sched_part, 20)
        progress_ms = _cpu_ms(lambda: _progress(api_part.sm, fetch_job_detail, job_id), api_part, 200)
        per_task = {k: round(1000 * totals[k] / tasks, 4)
                    for k in ("sched_py", "pg_sched", "redis", "pg_worker", "compaction_py", "pg_compaction")}
        # a fleet of `workers` beats every HEARTBEAT_INTERVAL_S (their Postgres side: a beat's Python is the
        # worker's); the reaper runs every 5 s; both spread over `rate` tasks/s
        per_task["heartbeats"] = round(
            beat_ms["postgres"] * args.workers / HEARTBEAT_INTERVAL_S / args.rate, 4
        )
        per_task["reaper"] = round(reap_ms["total"] / 5.0 / args.rate, 4)
        rows_read = walk["chunks"] * (walker.chunk_rows if walker is not None else 0)  # at most
        walk_row_ms = 1000 * walk["cpu_s"] / rows_read if rows_read else 0.0
        # the walk read every done row, none due (before 23's fix)
        walked_all = rows_read >= walk["done_rows"]
        if compactor is not None:
            # a pass a second (at most compact_pass_s of it): in steady state `rate` x compact_after_s rows
            # are done but not due; a walk that reads past them pays for them all, one that stops at them a
            # chunk or two
            steady_rows = (args.rate * settings.compact_after_s if walked_all
                           else rows_read / max(walk["passes"], 1))
            walk_pass_ms = min(1000 * settings.compact_pass_s, steady_rows * walk_row_ms)
            per_task["compaction_walk"] = round(walk_pass_ms / args.rate, 4)
        total = sum(per_task.values())
        return {
            "views": args.views, "cues": len(ROOM_CUES), "window": args.window, "rounds": args.rounds,
            "tasks_measured": tasks, "tasks_sent": int(totals["sent"]), "left_in_flight": args.leave,
            "transport": "prebuilt" if prebuilt else "kombu",
            "view_batches": bool(getattr(settings, "worker_batch_views", False)),
            "compaction": compactor is not None,
            "views_compacted": int(totals["views_compacted"]),
            "tasks_compacted": int(totals["tasks_compacted"]),
            "compaction_walk": {
                "cpu_us_per_row": round(1000 * walk_row_ms, 2), "passes": walk["passes"],
                "chunks": walk["chunks"], "done_rows": walk["done_rows"], "reads_past_not_due": walked_all,
            },
            "compact_after_s": settings.compact_after_s, "compact_pass_s": settings.compact_pass_s,
            "cpu_ms_per_task": {**per_task, "total": round(total, 4)},
            "one_core_tasks_per_s": round(1000 / total) if total else None,
            "fleet_assumed": {"workers": args.workers, "tasks_per_s": args.rate},
            "pass_ms": percentiles(passes_ms[1:]),
            "heartbeat_cpu_ms": beat_ms, "reaper_pass_cpu_ms": reap_ms, "progress_query_cpu_ms": progress_ms,
            "load_avg_1m": round(os.getloadavg()[0], 2),
        }
    finally:
        drop_database(url)
        red.close()


def _reap(sm: Any, reap_once: Any, settings: Any) -> None:
    with sm() as s:
        reap_once(s, queued_timeout_s=settings.lease_s, default_max_attempts=3, dead_after_s=10)


def _progress(sm: Any, fetch: Any, job_id: int) -> None:
    with sm() as s:
        fetch(s, owner="bench", job_id=job_id, rates=None)


def _cpu_ms(fn: Any, part: Part, n: int) -> dict[str, float]:
    """Mean CPU ms of `fn` in this process and in the part's backend over `n` calls (after one warm-up)."""
    fn()
    c0, p0 = time.process_time(), part.cpu()
    for _ in range(n):
        fn()
    py, pg = 1000 * (time.process_time() - c0) / n, 1000 * (part.cpu() - p0) / n
    return {"python": round(py, 3), "postgres": round(pg, 3), "total": round(py + pg, 3)}


def main(argv: list[str] | None = None) -> int:
    """Run and store the figures under orchestration_cpu[label] in orchestration_cpu.json."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, default=4000)
    p.add_argument("--window", type=int, default=2000, help="dispatch window and budget (tasks per pass)")
    p.add_argument("--rounds", type=int, default=6, help="measured dispatch passes (after one warm-up)")
    p.add_argument("--workers", type=int, default=1000, help="fleet size the heartbeat cost is scaled to")
    p.add_argument(
        "--rate", type=float, default=2000.0, help="fleet tasks/s the heartbeat/reaper costs are spread over"
    )
    p.add_argument(
        "--leave", type=float, default=0.0, help="fraction of the queued tasks left in flight per round"
    )
    p.add_argument("--no-view-batches", action="store_true", help="workers claim one task per message")
    p.add_argument("--no-compaction", action="store_true", help="leave out compaction of finished views")
    p.add_argument(
        "--kombu", action="store_true", help="publish through kombu (the path before prebuilt messages)"
    )
    p.add_argument("--label", default="now")
    p.add_argument("--key", default="orchestration_cpu", help="the key the run is stored under")
    p.add_argument("--out", type=Path, default=RESULTS / "orchestration_cpu.json")
    args = p.parse_args(argv)
    res = measure(args)
    print(json.dumps(res), flush=True)
    doc = json.loads(args.out.read_text()) if args.out.exists() else {"benchmark": "orchestration_cpu"}
    doc.setdefault(args.key, {})[args.label] = {
        **res, "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
