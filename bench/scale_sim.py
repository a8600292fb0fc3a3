"""Scale simulation (issue 11 item 17): hundreds of simulated workers against the real scheduler, Postgres and Redis.

A simulated worker is a thread that does what a real worker child does, through the same code: it pops a real
`render.cue` message (made by the real scheduler's CeleryTransport) from the real Redis queues, runs it with the
worker's TaskRunner (claim, record done, counters) whose compute step sleeps `--task-s` instead of rendering
and stores a few bytes, and has a real Heartbeat (worker row upsert every 5 s, lease extension when due; the beats of
a process's workers are driven by one thread there instead of one thread each). Workers are spread over a few
processes; each process shares a small connection pool, as a deployment of this size would share PgBouncer.
The scheduler is the real Scheduler loop (dispatch, reaper, completion) in its own process, planning a
synthetic plan (no mesh sampling) of `rgb, normal, depth_zbuffer` (4 tasks per view with the passes render).

For each worker count (default 100, 300, 1000), on a fresh database, for `--seconds`:
- dispatch: tasks sent per second by the scheduler, and the time its dispatch passes took;
- throughput: tasks done per second against the ideal workers / task_s (utilisation), queue wait p50/p99;
- heartbeats: beats per second, beat latency p50/p99, and Postgres' commits and row updates per second;
- reaper: `--kill-fraction` of the workers are "killed -9" mid-task a third of the way in (they stop without a
  word and stop beating): seconds until each of their tasks was requeued, with a 300 s lease and a
  `--heartbeat-timeout-s` heartbeat timeout (requeued at the timeout, not at lease expiry);
- progress query: p50/p99 of the API's job detail query (one statement) polled every 50 ms meanwhile.

What it showed first (results kept under `before` in scale.json): at 1,000 workers heartbeats fell behind (each
was a SELECT, an ORM UPDATE, a lease UPDATE of the task row and a commit waiting for the WAL flush) and live
workers were declared dead: the reaper requeued hundreds of tasks that were still running. Fixed: a beat is
one upsert, the task's lease is pushed only once a third of it has passed (liveness is the worker row's job
now), and worker connections commit without waiting for the flush. What limits next: claims and results wait on the row locks
of the job's few counter rows (`pg_active_backends_by_wait`: Lock:transactionid), held across a client round
trip; here the clients are threads starved of a shared 2-core host, so it shows far earlier than in a fleet of
real processes. Sharding the counter rows would remove it.

Writes bench/results/scale.json. Run: .venv/bin/python bench/scale_sim.py [--workers 100,300,1000] [--seconds 30]
"""

from __future__ import annotations

import argparse
import base64
import json
import multiprocessing as mp
import os
import platform
import random
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from sqlalchemy import func, select, text

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.fanout import create_database, drop_database, labelled_space, percentiles, synthetic_plan  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.jobs import create_job  # noqa: E402
from services.core.db.models import Space, Task  # noqa: E402
from services.core.domain.jobspec import JobSpec  # noqa: E402
from services.core.settings import Settings, get_settings  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.worker.claim import Claimed
from services.worker.heartbeat import Heartbeat  # noqa: E402
from services.worker.runner import TaskRunner
from services.worker.tasks import worker_engine  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
REDIS_URL = os.environ.get("OMNIDATA_BENCH_REDIS_URL", "redis://127.0.0.1:6379/12")
CUES = ["rgb", "normal", "depth_zbuffer"]
LEASE_S = 300
POOL_PER_PROCESS = 6  # Postgres connections per simulated-worker process (the server allows ~100 in all)


class Killed(BaseException):
    """A simulated kill -9: not an Exception, so the runner records nothing (a dead process cannot)."""


class SleepingRunner(TaskRunner):
    """The worker's TaskRunner with its compute step replaced by a sleep and a few stored bytes."""

    def __init__(self, *args: Any, task_s: float, killed: threading.Event, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.task_s = task_s
        self.killed = killed
        self.rng = random.Random(hash(self.worker_id))
        self.slept = 0.0

    def execute(self, t: Claimed) -> tuple[str, Any]:
        self.slept = self.task_s * self.rng.uniform(0.8, 1.2)
        if self.killed.wait(self.slept):
            raise Killed(t.id)
        key = f"sim/{t.job_id}/{t.cue}/{t.point}_{t.view}"
        return key, self.store.put_bytes(key, f"{t.id}".encode())


def pct(xs: list[float]) -> dict[str, float] | None:
    """p50/p99/max in ms (fanout's percentiles), None without samples."""
    return percentiles(xs) if xs else None


def task_id_of(raw: bytes) -> int:
    """The task id in a Celery protocol-2 message as kombu stores it in Redis (base64 JSON body)."""
    env = json.loads(raw)
    return int(json.loads(base64.b64decode(env["body"]))[0][0])


def worker_process(
    index: int, n_workers: int, settings: Settings, redis_url: str, task_s: float, kill_ids: list[str],
    kill_at: Any, stop: Any, out: Any,
) -> None:
    """`n_workers` simulated workers (threads) sharing one connection pool; reports stats into `out`."""
    import redis

    engine = worker_engine(settings.database_url, pool_size=POOL_PER_PROCESS, max_overflow=0, pool_timeout=120)
    sm = make_sessionmaker(engine)
    store = LocalStore(settings.data_dir / "objects")
    queues = [settings.queue_render, settings.queue_derive]
    lock = threading.Lock()
    stats: dict[str, Any] = {"done": 0, "skipped": 0, "killed": [], "beat_s": [], "overhead_s": []}
    beats: list[tuple[Heartbeat, threading.Event]] = []

    def run_worker(k: int) -> None:
        wid = f"sim-{index}-{k}"
        killed = threading.Event()
        hb = Heartbeat(sm, wid, queues=queues, lease_s=LEASE_S)
        runner = SleepingRunner(sm, store, settings, wid, heartbeat=hb, task_s=task_s, killed=killed)
        with lock:
            beats.append((hb, killed))
        r = redis.Redis.from_url(redis_url)
        while not stop.is_set() and not killed.is_set():
            got = r.brpop(queues, timeout=1)
            if got is None:
                continue
            tid = task_id_of(got[1])
            t = time.perf_counter()
            runner.slept = 0.0
            try:
                outcome = runner.run(tid)
            except Killed:
                with lock:
                    stats["killed"].append(tid)
                break  # dead: no more tasks, no more beats
            with lock:
                stats["done" if outcome.status == "done" else "skipped"] += 1
                stats["overhead_s"].append(time.perf_counter() - t - runner.slept)  # claim + record, not the work
        r.close()

    def drive_heartbeats() -> None:
        # Each worker beats every interval, spread evenly over the interval (real workers start at random times).
        interval = beats[0][0].interval_s if beats else 5.0
        while not stop.is_set():
            t0 = time.monotonic()
            for k, (hb, killed) in enumerate(list(beats)):
                if stop.is_set():
                    break
                if not killed.is_set():
                    t = time.perf_counter()
                    try:
                        hb.beat()
                    except Exception:
                        pass
                    with lock:
                        stats["beat_s"].append(time.perf_counter() - t)
                wait = t0 + interval * (k + 1) / len(beats) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)

    def watch_kill() -> None:  # mid-task, the sleeping runner wakes up dead; between tasks, the loop stops
        kill_at.wait()
        for hb, killed in list(beats):
            if hb.worker_id in kill_ids:
                killed.set()

    threads = [threading.Thread(target=run_worker, args=(k,), daemon=True) for k in range(n_workers)]
    for t in threads:
        t.start()
    while len(beats) < n_workers:
        time.sleep(0.05)
    helpers = [threading.Thread(target=drive_heartbeats, daemon=True), threading.Thread(target=watch_kill, daemon=True)]
    for t in helpers:
        t.start()
    stop.wait()
    kill_at.set()  # release the watcher
    for t in threads:
        t.join(10)
    out.put({k: v for k, v in stats.items()})
    engine.dispose()


class CountingTransport:
    """The scheduler's CeleryTransport, counting what it sends and how long its sends take."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.sent = 0
        self.send_s = 0.0

    def send(self, batch: Any) -> None:
        t = time.perf_counter()
        self.inner.send(batch)
        self.send_s += time.perf_counter() - t
        self.sent += len(batch)


def scheduler_process(settings: Settings, plan: Any, stop: Any, out: Any) -> None:
    """The real Scheduler loop (plan, dispatch, reap, complete) with the synthetic plan; reports its counts."""
    from services.scheduler.loop import Scheduler
    from services.scheduler.transport import CeleryTransport

    engine = make_engine(settings.database_url, pool_size=2)
    transport = CountingTransport(CeleryTransport(settings=settings))
    sched = Scheduler(make_sessionmaker(engine), LocalStore(settings.data_dir / "objects"), transport, settings,
                      "sim-scheduler", plan_fn=lambda *_a: plan, cache_dir=settings.data_dir / "cache")
    passes: list[float] = []
    reaped = 0
    original = sched.dispatch_once
    original_reap = sched.reap_once

    def timed_dispatch() -> Any:
        t = time.perf_counter()
        res = original()
        passes.append(time.perf_counter() - t)
        return res

    def counted_reap() -> Any:
        nonlocal reaped
        res = original_reap()
        reaped += res.expired_retried
        return res

    sched.dispatch_once = timed_dispatch  # type: ignore[method-assign]
    sched.reap_once = counted_reap  # type: ignore[method-assign]
    sched.run_forever(stop, interval=0.2)
    out.put({"sent": transport.sent, "send_s": transport.send_s, "passes": passes, "reaped": reaped})
    transport.inner.close()
    engine.dispose()


def pg_stats(sm: Any, db: str) -> dict[str, int]:
    """Cumulative commits of the database and row updates of the worker and task tables."""
    with sm() as s:
        commits = s.scalar(text("SELECT xact_commit FROM pg_stat_database WHERE datname = :d"), {"d": db})
        ups = dict(s.execute(text(
            "SELECT relname, n_tup_upd + n_tup_ins FROM pg_stat_user_tables WHERE relname IN ('worker', 'task')"
        )).all())
    return {"commits": int(commits or 0), "worker_rows": int(ups.get("worker", 0)), "task_rows": int(ups.get("task", 0))}


def run_config(args: argparse.Namespace, n_workers: int) -> dict[str, Any]:
    """One worker count on a fresh database and Redis db; returns its figures."""
    import redis

    from services.api.jobs.service import fetch_job_detail

    r = redis.Redis.from_url(args.redis)
    r.flushdb()
    db_url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="omnidata-scale-sim-"))
    ctx = mp.get_context("spawn")  # no inherited connections
    try:
        migrate(db_url)
        settings = get_settings(
            data_dir=tmp, database_url=db_url, broker_url=args.redis, storage_url=f"file://{tmp}/objects",
            lease_s=LEASE_S, heartbeat_timeout_s=args.heartbeat_timeout_s, dispatch_window=max(20, 2 * n_workers),
        )
        engine = make_engine(db_url, pool_size=2)
        sm = make_sessionmaker(engine)
        store = LocalStore(tmp / "objects")
        # enough views that the job outlasts the run: every worker busy all the time, 4 tasks per view
        n_views = int(1.5 * n_workers * args.seconds / args.task_s / len(CUES)) + 100
        plan = synthetic_plan("scale", n_views // 4 + 1, 4, resolution=32)
        space_id = labelled_space(sm, store, "scale")
        with sm() as s:
            job = create_job(s, owner="bench", spec=JobSpec(cues=CUES, name="scale"), spaces=[s.get(Space, space_id)])
            s.commit()
            job_id = job.id

        stop = ctx.Event()
        kill_at = ctx.Event()
        outq = ctx.Queue()
        per_proc = -(-n_workers // args.processes)
        counts = [min(per_proc, n_workers - p * per_proc) for p in range(args.processes)]
        all_ids = [f"sim-{p}-{k}" for p in range(args.processes) for k in range(counts[p])]
        kill_ids = random.Random(7).sample(all_ids, max(1, int(args.kill_fraction * n_workers)))
        sched = ctx.Process(target=scheduler_process, args=(settings, plan, stop, outq))
        sched.start()
        procs = [ctx.Process(target=worker_process, args=(p, counts[p], settings, args.redis, args.task_s, kill_ids,
                                                          kill_at, stop, outq)) for p in range(args.processes)]
        for p in procs:
            p.start()

        def count(state: str) -> int:
            with sm() as s:
                return int(s.scalar(select(func.count()).select_from(Task).where(
                    Task.job_id == job_id, Task.state == state)) or 0)

        deadline = time.monotonic() + 120
        while count("running") < n_workers // 2 and time.monotonic() < deadline:
            time.sleep(0.5)  # planned, dispatched, workers started
        t0, done0, stats0 = time.monotonic(), count("done"), pg_stats(sm, engine.url.database or "")
        progress_lat: list[float] = []
        requeued: dict[int, float] = {}
        held: list[int] = []
        killed_at: float | None = None
        waits_pg: dict[str, int] = {}
        next_wait_sample = 0.0
        with sm() as s:
            while time.monotonic() - t0 < args.seconds:
                t = time.perf_counter()
                fetch_job_detail(s, owner="bench", job_id=job_id, rates=None)
                s.rollback()
                progress_lat.append(time.perf_counter() - t)
                if time.monotonic() >= next_wait_sample:  # what Postgres' busy backends are waiting for
                    next_wait_sample = time.monotonic() + 0.5
                    for kind, n in s.execute(text(
                        "SELECT coalesce(wait_event_type || ':' || wait_event, 'CPU'), count(*) FROM pg_stat_activity "
                        "WHERE datname = current_database() AND state = 'active' AND pid <> pg_backend_pid() GROUP BY 1"
                    )):
                        waits_pg[kind] = waits_pg.get(kind, 0) + int(n)
                    s.rollback()
                if killed_at is None and time.monotonic() - t0 >= args.seconds / 3:
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
        with sm() as s:
            waits = [(b - a).total_seconds() for a, b in s.execute(select(Task.queued_at, Task.started_at).where(
                Task.job_id == job_id, Task.started_at.is_not(None), Task.queued_at.is_not(None)))]
        stop.set()
        results = [outq.get(timeout=120) for _ in range(args.processes + 1)]
        for p in [sched, *procs]:
            p.join(30)
        sched_stats = next(x for x in results if "sent" in x)
        wstats = [x for x in results if "beat_s" in x]
        beat_s = [b for w in wstats for b in w["beat_s"]]
        overhead_s = [b for w in wstats for b in w["overhead_s"]]
        with sm() as s:
            s.execute(text("UPDATE job SET state = 'cancelled' WHERE id = :j"), {"j": job_id})
            s.commit()
        engine.dispose()
        rate = (done1 - done0) / elapsed
        return {
            "workers": n_workers,
            "processes": args.processes,
            "task_s": args.task_s,
            "measured_s": round(elapsed, 1),
            "tasks_done": done1 - done0,
            "tasks_per_s": round(rate, 1),
            "ideal_tasks_per_s": round(n_workers / args.task_s, 1),
            "utilisation": round(rate * args.task_s / n_workers, 3),
            "queue_wait": pct(waits),
            "task_overhead": pct(overhead_s),  # a worker's claim + record done (pool wait included), per task
            "pg_active_backends_by_wait": dict(sorted(waits_pg.items(), key=lambda kv: -kv[1])),
            "dispatch": {
                "tasks_sent": sched_stats["sent"],
                "sent_per_s_over_run": round(sched_stats["sent"] / max(elapsed, 1e-9), 1),
                "passes": len(sched_stats["passes"]),
                "pass_ms": pct(sched_stats["passes"]),
                "broker_send_s_total": round(sched_stats["send_s"], 2),
            },
            "heartbeats": {
                "beats_per_s": round(len(beat_s) / max(elapsed, 1e-9), 1),
                "beat_ms": pct(beat_s),
                "pg_commits_per_s": round((stats1["commits"] - stats0["commits"]) / elapsed, 1),
                "pg_worker_row_writes_per_s": round((stats1["worker_rows"] - stats0["worker_rows"]) / elapsed, 1),
                "pg_task_row_writes_per_s": round((stats1["task_rows"] - stats0["task_rows"]) / elapsed, 1),
            },
            "reaper": {
                "killed_workers": len(kill_ids),
                "tasks_held_by_killed": len(held),
                "requeued": len(requeued),
                "requeue_after_kill_s": {"max": round(max(requeued.values()), 1),
                                         "mean": round(sum(requeued.values()) / len(requeued), 1)}
                if requeued else None,
                "heartbeat_timeout_s": args.heartbeat_timeout_s,
                "lease_s": LEASE_S,
                "reaped_total": sched_stats["reaped"],
            },
            "progress_query": pct(progress_lat),
            "load_avg_1m": round(os.getloadavg()[0], 2),
        }
    finally:
        drop_database(db_url)
        r.flushdb()


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run each worker count, write bench/results/scale.json."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", default="100,300,1000", help="comma-separated simulated worker counts")
    p.add_argument("--seconds", type=float, default=30.0, help="measured seconds per worker count")
    p.add_argument("--task-s", type=float, default=5.0, help="seconds a simulated task sleeps (+-20%%)")
    p.add_argument("--processes", type=int, default=4, help="processes the simulated workers are spread over")
    p.add_argument("--kill-fraction", type=float, default=0.02)
    p.add_argument("--heartbeat-timeout-s", type=int, default=10)
    p.add_argument("--redis", default=REDIS_URL)
    p.add_argument("--label", default="", help="a note stored with the results (e.g. before/after a change)")
    p.add_argument("--out", type=Path, default=RESULTS / "scale.json")
    p.add_argument("--before", type=Path, default=None,
                   help="an earlier run's JSON (e.g. before a fix), kept in the results under `before`")
    args = p.parse_args(argv)
    before = json.loads(args.before.read_text()) if args.before else None
    configs = []
    for n in [int(x) for x in args.workers.split(",") if x.strip()]:
        res = run_config(args, n)
        print(json.dumps(res), flush=True)
        configs.append(res)
    doc = {"benchmark": "scale_sim", "label": args.label, "configs": configs, "python": platform.python_version(),
           "cpus": os.cpu_count(), "note": "one shared host runs Postgres, Redis, the scheduler and every simulated "
           "worker; figures are floors, not capacity"}
    if before is not None:
        doc["before"] = {"label": before.get("label", ""), "configs": before.get("configs", [])}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
