"""Scale simulation: hundreds of simulated workers against the real scheduler, Postgres and Redis.

A simulated worker is a thread that does what a real worker child does, through the same code
(bench/lib/scale_procs.py): it pops a real `render.cue` message (made by the real scheduler's CeleryTransport)
from Redis, runs it with the worker's TaskRunner (claim, record done, counters) whose compute step sleeps
instead of rendering and stores a few bytes, and has a real Heartbeat. Workers are spread over a few
processes, each sharing a small connection pool (as a deployment of this size would share PgBouncer). The
scheduler is the real Scheduler loop in its own process, with a synthetic plan (no mesh sampling), 4 views per
point.

The grain (default): the 18 cues of an unlabelled room, each task sleeping its cue's measured time
(bench/scale_cost.CUE_SECONDS: the render ~0.3 s, derivations 5-200 ms; 0.059 s a task on average), so 1,000
workers ideally finish ~17,000 tasks/s. `--task-s S` instead gives every task S seconds (+-20%) of `rgb,
normal, depth_zbuffer` (the first figures, kept at the top level of scale_sim.json).

For each worker count (default 100, 300, 1000), on a fresh database and a private redis-server, for
`--seconds`:
- throughput: tasks done per second against the ideal (utilisation), queue wait and task overhead p50/p99;
- orchestration CPU: CPU seconds (/proc) of the scheduler, of the Postgres backends (by client: scheduler,
  workers, api) and of Redis, per task done, and the tasks/s one orchestrator core would sustain at that cost;
- where Postgres waits (pg_stat_activity sampled every 0.5 s), dispatch pass times, heartbeat writes;
- reaper: `--kill-fraction` of the workers are "killed -9" a third of the way in: seconds until their tasks
  came back;
- progress query: p50/p99 of the API's job detail query polled every 50 ms meanwhile.

History (scale_sim.json keeps every step): 5-second tasks first showed heartbeats falling behind at 1,000
workers (fixed: a beat is one upsert). At the real grain (`steps`), claims and results queued on the row locks
of the job's few counter rows (Lock:transactionid); step 1 shards those rows and moves tasks and counters in
one statement; step 2 makes a worker's claim and result one fixed SQL statement each (SQLAlchemy compiled them
anew on every call: ~2 ms of worker CPU per move, its ON CONFLICT construct cannot be cached). What limits
next is the dispatch pass: a readiness lookup per pending row, cue by cue.

Writes bench/results/scale_sim.json. Run: .venv/bin/python bench/scale/scale_sim.py [--workers 100,300,1000]
    [--seconds 30] [--step NAME --label TEXT]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import random
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from sqlalchemy import func, select, text

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.scale_cost import (  # noqa: E402
    ROOM_CUES,
    PrivateRedis,
    ProcessCpu,
    backend_pids,
    cpu_seconds,
    mean_task_seconds,
    publish_cost,
    sample_waits,
    with_app_name,
)
from bench.lib.scale_procs import LEASE_S, isolated_overhead, scheduler_process, worker_process  # noqa: E402
from bench.scale.fanout import (  # noqa: E402
    create_database,
    drop_database,
    labelled_space,
    percentiles,
    synthetic_plan,
)
from services.core.db.counters import job_progress  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.jobs import create_job  # noqa: E402
from services.core.db.models import Space, Task  # noqa: E402
from services.core.db.states import transition  # noqa: E402
from services.core.domain.jobspec import JobSpec  # noqa: E402
from services.core.settings import get_settings  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402

RESULTS = results_dir()
CUES = ["rgb", "normal", "depth_zbuffer"]


def pct(xs: list[float]) -> dict[str, float] | None:
    """p50/p99/max in ms (fanout's percentiles), None without samples."""
    return percentiles(xs) if xs else None


def run_delay(backend_pid: int) -> float:
    """Seconds this thread and the Postgres backend `backend_pid` have waited runnable for a CPU so far
    (/proc schedstat, nanoseconds; 0 where the kernel does not keep it)."""
    total = 0.0
    for path in ("/proc/thread-self/schedstat", f"/proc/{backend_pid}/schedstat"):
        try:
            total += int(Path(path).read_text().split()[1]) / 1e9
        except (OSError, IndexError, ValueError):
            pass
    return total


def pg_stats(sm: Any, db: str) -> dict[str, int]:
    """Cumulative commits of the database and row updates of the worker and task tables."""
    with sm() as s:
        commits = s.scalar(text("SELECT xact_commit FROM pg_stat_database WHERE datname = :d"), {"d": db})
        ups = dict(
            s.execute(
                text(
                    "SELECT relname, n_tup_upd + n_tup_ins FROM pg_stat_user_tables WHERE relname IN "
                    "('worker', 'task')"
                )
            ).all()
        )
    return {
        "commits": int(commits or 0), "worker_rows": int(ups.get("worker", 0)),
        "task_rows": int(ups.get("task", 0)),
    }


def run_config(args: argparse.Namespace, n_workers: int) -> dict[str, Any]:
    """One worker count on a fresh database and Redis db; returns its figures."""
    import redis

    from services.api.jobs.service import fetch_job_detail

    r = redis.Redis.from_url(args.redis)
    r.flushdb()
    db_url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="omnidata-scale-sim-"))
    ctx = mp.get_context("spawn")  # no inherited connections
    real_grain = args.task_s <= 0
    cues = ROOM_CUES if real_grain else CUES
    mean_s = mean_task_seconds(cues) if real_grain else args.task_s
    try:
        migrate(db_url)
        settings = get_settings(
            data_dir=tmp, database_url=db_url, broker_url=args.redis, storage_url=f"file://{tmp}/objects",
            lease_s=LEASE_S, heartbeat_timeout_s=args.heartbeat_timeout_s,
            dispatch_window=args.window or max(20, 2 * n_workers),
            compact_views=args.compact_after_s >= 0, compact_after_s=max(args.compact_after_s, 0.0),
        )
        engine = make_engine(with_app_name(db_url, "api"), pool_size=2)  # the progress poller (and the bench)
        sm = make_sessionmaker(engine)
        store = LocalStore(tmp / "objects")
        # enough views that the job outlasts the run even at the ideal rate (4 views per point)
        tasks_per_view = len(cues) + 1
        n_views = int(1.5 * n_workers * (args.seconds + 60) / mean_s / tasks_per_view) + 100
        # ... but no more than this host can plan and get through (at the ideal rate of 1,000 workers the job
        # would be 2M tasks, and the planner would still be persisting them when the measurement starts)
        n_views = min(n_views, args.max_views)
        plan = synthetic_plan("scale", n_views // 4 + 1, 4, resolution=32)
        space_id = labelled_space(sm, store, "scale")
        with sm() as s:
            job = create_job(
                s, owner="bench", spec=JobSpec(cues=cues, name="scale"), spaces=[s.get(Space, space_id)]
            )
            s.commit()
            job_id = job.id

        stop = ctx.Event()
        kill_at = ctx.Event()
        measuring = ctx.Event()  # workers record beats and overheads from t0 on
        outq = ctx.Queue()
        per_proc = -(-n_workers // args.processes)
        counts = [min(per_proc, n_workers - p * per_proc) for p in range(args.processes)]
        all_ids = [f"sim-{p}-{k}" for p in range(args.processes) for k in range(counts[p])]
        kill_ids = random.Random(7).sample(all_ids, max(1, int(args.kill_fraction * n_workers)))
        sched_settings = settings.model_copy(update={"database_url": with_app_name(db_url, "scheduler")})
        worker_settings = settings.model_copy(update={"database_url": with_app_name(db_url, "workers")})
        sched = ctx.Process(target=scheduler_process, args=(sched_settings, plan, stop, outq))
        sched.start()
        procs = [
            ctx.Process(
                target=worker_process,
                args=(
                    p, counts[p], worker_settings, args.redis, args.task_s, kill_ids, kill_at, stop, outq,
                    measuring, args.worker_nice,
                ),
            )
            for p in range(args.processes)
        ]
        # one more worker, alone in its process at normal priority (a real worker's view of the task overhead)
        procs.append(
            ctx.Process(
                target=worker_process,
                args=(
                    args.processes, 1, worker_settings, args.redis, args.task_s, [], kill_at, stop, outq,
                    measuring, 0, True,
                ),
            )
        )
        for p in procs:
            p.start()

        def count(state: str) -> int:
            if state == "done":  # from the counters: compaction deletes done task rows, not their counts
                with sm() as s:
                    return sum(c.get("done", 0) for c in job_progress(s, job_id).values())
            with sm() as s:
                return int(s.scalar(select(func.count()).select_from(Task).where(
                    Task.job_id == job_id, Task.state == state)) or 0)

        deadline = time.monotonic() + 300
        while count("running") < n_workers // 2 and time.monotonic() < deadline:
            time.sleep(0.5)  # planned, dispatched, workers started
        time.sleep(args.warmup)

        def groups() -> dict[str, list[int]]:
            with sm() as s:
                pg = backend_pids(s)
            return {
                "scheduler": [int(sched.pid or 0)], "postgres": [p for ps in pg.values() for p in ps],
                "redis": [args.redis_pid] if args.redis_pid else [],
                "sim_workers": [int(p.pid or 0) for p in procs],
                **pg,
            }

        cpu = ProcessCpu()
        cpu.start(groups())
        measuring.set()
        t0, done0, stats0 = time.monotonic(), count("done"), pg_stats(sm, engine.url.database or "")
        progress_lat: list[float] = []
        requeued: dict[int, float] = {}
        held: list[int] = []
        killed_at: float | None = None
        waits_pg: dict[str, int] = {}
        next_wait_sample = 0.0
        progress_cpu: list[float] = []
        progress_runq: list[float] = []  # time the poller thread and its backend sat runnable without a CPU
        # GET /jobs/{id}'s own work (services.api.jobs.endpoints.get_job): an autocommit read session, one
        # statement, the JSON; its wall time, and its CPU (this thread's plus its Postgres backend's)
        poll_engine = make_engine(with_app_name(db_url, "api"), pool_size=1, max_overflow=0)
        read_sm = make_sessionmaker(poll_engine.execution_options(isolation_level="AUTOCOMMIT"))
        with read_sm() as probe_session:
            api_pid = int(probe_session.scalar(text("SELECT pg_backend_pid()")) or 0)
        with sm() as s:
            while time.monotonic() - t0 < args.seconds:
                t, c, pc = time.perf_counter(), time.thread_time(), cpu_seconds(api_pid)
                rq = run_delay(api_pid)
                with read_sm() as rs:
                    fetch_job_detail(rs, owner="bench", job_id=job_id, rates=None).model_dump_json()
                progress_lat.append(time.perf_counter() - t)
                progress_cpu.append(time.thread_time() - c + cpu_seconds(api_pid) - pc)
                progress_runq.append(run_delay(api_pid) - rq)
                if time.monotonic() >= next_wait_sample:  # what Postgres' busy backends are waiting for
                    next_wait_sample = time.monotonic() + 0.5
                    sample_waits(s, waits_pg)
                if args.kill_fraction > 0 and killed_at is None and time.monotonic() - t0 >= args.seconds / 3:
                    held = [int(i) for (i,) in s.execute(select(Task.id).where(
                        Task.state == "running", Task.worker_id.in_(kill_ids)))]
                    kill_at.set()
                    killed_at = time.monotonic()
                elif killed_at is not None and len(requeued) < len(held):
                    back = s.execute(select(Task.id).where(
                        Task.id.in_([i for i in held if i not in requeued]),
                        (Task.state != "running") | Task.worker_id.not_in(kill_ids))).all()
                    for (i,) in back:
                        requeued[int(i)] = time.monotonic() - killed_at
                    s.rollback()
                time.sleep(0.05)
        elapsed = time.monotonic() - t0
        done1, stats1 = count("done"), pg_stats(sm, engine.url.database or "")
        cpu_s = cpu.stop(groups())
        with sm() as s:
            waits = [
                (b - a).total_seconds()
                for a, b in s.execute(
                    select(Task.queued_at, Task.started_at).where(
                        Task.job_id == job_id, Task.started_at.is_not(None), Task.queued_at.is_not(None)
                    )
                )
            ]
        measuring.clear()
        stop.set()
        kill_at.set()
        results = [outq.get(timeout=180) for _ in range(len(procs) + 1)]
        for p in [sched, *procs]:
            p.join(30)
        sched_stats = next(x for x in results if "sent" in x)
        wstats = [x for x in results if "beat_s" in x and not x["probe"]]
        probe_overhead_s = [b for w in results if w.get("probe") for b in w["overhead_s"]]
        beat_s = [b for w in wstats for b in w["beat_s"]]
        overhead_s = [b for w in wstats for b in w["overhead_s"]]
        message_overhead_s = [b for w in wstats for b in w["message_overhead_s"]]
        with sm() as s:  # one worker alone, on the same database, once the fleet has stopped
            alone = list(s.scalars(select(Task.id).where(Task.job_id == job_id, Task.state == "pending")
                                   .order_by(Task.id).limit(500)))
            transition(s, job_id=job_id, task_ids=alone, from_state="pending", to_state="queued")
            s.commit()
        overhead_alone, alone_pg_ms = isolated_overhead(
            with_app_name(db_url, "alone"), worker_settings, alone
        )
        with sm() as s:
            s.execute(text("UPDATE job SET state = 'cancelled' WHERE id = :j"), {"j": job_id})
            s.commit()
        engine.dispose()
        poll_engine.dispose()
        n_done = done1 - done0
        rate = n_done / elapsed
        orchestration_s = cpu_s["scheduler"] + cpu_s["postgres"] + cpu_s["redis"]
        per_task_ms = 1000 * orchestration_s / max(n_done, 1)
        return {
            "workers": n_workers,
            "processes": args.processes,
            "grain": "real (per-cue times of a room, CUE_SECONDS)"
            if real_grain
            else f"{args.task_s} s per task",
            "mean_task_s": round(mean_s, 4),
            "dispatch_window": settings.dispatch_window,
            "measured_s": round(elapsed, 1),
            "tasks_done": n_done,
            "tasks_per_s": round(rate, 1),
            "ideal_tasks_per_s": round(n_workers / mean_s, 1),
            "utilisation": round(rate * mean_s / n_workers, 3),
            # of the task rows still there at the end (compaction removed older ones)
            "queue_wait": pct(waits),
            "task_overhead": pct(overhead_s),  # a worker's claim + record done (pool wait included), per task
            # per message: a whole view (render + the rest of the view claimed and recorded) is one message
            "message_overhead": pct(message_overhead_s),
            # one worker in its own process, under the load
            "task_overhead_probe_worker": pct(probe_overhead_s),
            "worker_nice": args.worker_nice,
            # the same without the fleet's contention
            "task_overhead_one_worker_alone": pct(overhead_alone[20:]),
            # its claim + result statements
            "postgres_cpu_ms_per_task_one_worker_alone": round(alone_pg_ms, 3),
            "cpu_s": cpu_s,
            "orchestration_cpu_ms_per_task": {
                "total": round(per_task_ms, 3),
                **{k: round(1000 * cpu_s[k] / max(n_done, 1), 3) for k in ("scheduler", "postgres", "redis")},
                "sim_workers": round(1000 * cpu_s["sim_workers"] / max(n_done, 1), 3),
                **{k: round(1000 * v / max(n_done, 1), 3) for k, v in cpu_s.items() if k.startswith("pg:")},
            },
            "one_orchestrator_core_tasks_per_s": round(1000 / per_task_ms, 0) if per_task_ms > 0 else None,
            "pg_active_backends_by_wait": dict(sorted(waits_pg.items(), key=lambda kv: -kv[1])),
            "dispatch": {
                "tasks_sent": sched_stats["sent"],
                "sent_per_s_over_run": round(sched_stats["sent"] / max(elapsed, 1e-9), 1),
                "passes": len(sched_stats["passes"]),
                "pass_ms": pct(sched_stats["passes"]),
                "broker_send_s_total": round(sched_stats["send_s"], 2),
            },
            "compaction": {
                "after_s": args.compact_after_s if args.compact_after_s >= 0 else None,
                "views": sched_stats["compacted_views"], "tasks": sched_stats["compacted_tasks"],
                "passes": len(sched_stats["compact_passes"]), "pass_ms": pct(sched_stats["compact_passes"]),
                # over the whole run, warm-up included
                "scheduler_cpu_s": round(sched_stats["compact_cpu_s"], 3),
            },
            "heartbeats": {
                "beats_per_s": round(len(beat_s) / max(elapsed, 1e-9), 1),
                "beat_ms": pct(beat_s),
                "pg_commits_per_s": round((stats1["commits"] - stats0["commits"]) / elapsed, 1),
                "pg_worker_row_writes_per_s": round(
                    (stats1["worker_rows"] - stats0["worker_rows"]) / elapsed, 1
                ),
                "pg_task_row_writes_per_s": round((stats1["task_rows"] - stats0["task_rows"]) / elapsed, 1),
            },
            "reaper": {
                "killed_workers": len(kill_ids) if args.kill_fraction > 0 else 0,
                "tasks_held_by_killed": len(held),
                "requeued": len(requeued),
                "requeue_after_kill_s": {
                    "max": round(max(requeued.values()), 1),
                    "mean": round(sum(requeued.values()) / len(requeued), 1),
                }
                if requeued
                else None,
                "heartbeat_timeout_s": args.heartbeat_timeout_s,
                "lease_s": LEASE_S,
                "reaped_total": sched_stats["reaped"],
            },
            "progress_query": pct(progress_lat),
            # the poller thread's + its Postgres backend's CPU per query
            "progress_query_cpu": pct(progress_cpu),
            # (the backend's from /proc, in 10 ms ticks: a query's p99 is a tick; the mean is what it costs)
            "progress_query_cpu_mean_ms": round(1000 * sum(progress_cpu) / max(len(progress_cpu), 1), 3),
            # CPU starvation (schedstat run_delay) per query
            "progress_query_runqueue_wait": pct(progress_runq),
            "load_avg_1m": round(os.getloadavg()[0], 2),
        }
    finally:
        drop_database(db_url)
        r.flushdb()


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run each worker count, write bench/results/scale_sim.json."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", default="100,300,1000", help="comma-separated simulated worker counts")
    p.add_argument("--seconds", type=float, default=30.0, help="measured seconds per worker count")
    p.add_argument("--task-s", type=float, default=0.0,
                   help="seconds a simulated task sleeps (+-20%%); 0 (default): the real per-cue grain")
    p.add_argument("--processes", type=int, default=4, help="processes the simulated workers are spread over")
    p.add_argument("--kill-fraction", type=float, default=0.02)
    p.add_argument("--heartbeat-timeout-s", type=int, default=10)
    p.add_argument("--window", type=int, default=0, help="dispatch window (0: 2 x workers, at least 20)")
    p.add_argument("--max-views", type=int, default=20_000, help="views of the simulated job at most")
    p.add_argument(
        "--worker-nice", type=int, default=10,
        help="niceness of the simulated-worker processes (a real fleet's CPU is not the orchestrator's)",
    )
    p.add_argument(
        "--compact-after-s", type=float, default=5.0,
        help="compact_after_s of the scheduler (the product's 60 s would compact nothing "
        "in a short run); negative: compaction off",
    )
    p.add_argument(
        "--warmup", type=float, default=5.0, help="seconds after the workers got busy before measuring"
    )
    p.add_argument(
        "--redis", default="", help="a running Redis (default: a private redis-server, CPU ours alone)"
    )
    p.add_argument("--step", default="",
                   help="store the run under steps[STEP] of the results (each bottleneck removed is a step), "
                        "keeping every other figure there; without it the top-level configs are replaced")
    p.add_argument("--label", default="", help="a note stored with the results (e.g. before/after a change)")
    p.add_argument(
        "--key", default="", help="store the run under KEY[LABEL] of the results, every other key kept"
    )
    p.add_argument("--publish-cost", action="store_true",
                   help="also measure the CPU per message of publishing alone (stored under `publishing`)")
    p.add_argument("--out", type=Path, default=RESULTS / "scale_sim.json")
    p.add_argument("--before", type=Path, default=None,
                   help="an earlier run's JSON (e.g. before a fix), kept in the results under `before`")
    args = p.parse_args(argv)
    before = json.loads(args.before.read_text()) if args.before else None
    private = None
    args.redis_pid = 0
    if not args.redis:
        private = PrivateRedis()
        args.redis, args.redis_pid = private.url, private.pid
    configs = []
    try:
        for n in [int(x) for x in args.workers.split(",") if x.strip()]:
            res = run_config(args, n)
            print(json.dumps(res), flush=True)
            configs.append(res)
    finally:
        if private is not None:
            private.close()
    doc = json.loads(args.out.read_text()) if args.out.exists() else {"benchmark": "scale_sim"}
    if args.key:
        doc.setdefault(args.key, {})[args.label or "run"] = {
            "configs": configs, "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    elif args.step:
        doc.setdefault("steps", {})[args.step] = {
            "label": args.label, "configs": configs,
            "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    else:
        doc.update({"label": args.label, "configs": configs})
        if before is not None:
            doc["before"] = {"label": before.get("label", ""), "configs": before.get("configs", [])}
    if args.publish_cost:
        doc["publishing"] = publish_cost()
        print(json.dumps(doc["publishing"]))
    doc.update(
        {
            "python": platform.python_version(), "cpus": os.cpu_count(),
            "note": "one shared host (2 cores, "
            "seven other developers' work) runs Postgres, Redis, the scheduler and every simulated worker; "
            "figures are floors, not capacity",
        }
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
