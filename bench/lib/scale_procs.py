"""The processes of the scale simulation (bench/scale/scale_sim.py): simulated workers and the real scheduler.

A simulated worker is a thread running the worker's real TaskRunner (claim, record done, counters) whose
compute step sleeps instead of rendering (`SleepingRunner`), fed with real `render.cue` messages popped from
Redis, with a real Heartbeat; a process hosts many of them around one small connection pool. The scheduler
process runs the real Scheduler loop with a synthetic plan and counts what it sends and how long its dispatch
passes take.
"""

from __future__ import annotations

import base64
import json
import random
import threading
import time
from typing import Any

from bench.lib.scale_cost import task_seconds
from services.core.db.engine import make_engine, make_sessionmaker
from services.core.settings import Settings
from services.core.storage import LocalStore
from services.worker.run.claim import Claimed
from services.worker.run.heartbeat import Heartbeat
from services.worker.run.runner import TaskRunner
from services.worker.tasks import worker_engine

LEASE_S = 300
POOL_PER_PROCESS = 6  # Postgres connections per simulated-worker process (the server allows ~100 in all)


class Killed(BaseException):
    """A simulated kill -9: not an Exception, so the runner records nothing (a dead process cannot)."""


class SleepingRunner(TaskRunner):
    """The worker's TaskRunner with its compute step replaced by a sleep and a few stored bytes.

    `task_s` > 0: every task sleeps task_s +-20%; 0: the real grain, each cue its measured time (CUE_SECONDS).
    """

    def __init__(self, *args: Any, task_s: float, killed: threading.Event, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.task_s = task_s
        self.killed = killed
        self.rng = random.Random(hash(self.worker_id))
        self.slept = 0.0

    def render_view(self, t: Claimed) -> str:
        """The whole-view path's render (kept in memory, nothing stored): the `passes` task's sleep."""
        return self._sleep(t)

    def make(self, t: Claimed) -> tuple[str, bytes]:
        """The compute step every path takes (execute and the view batches' _compute): a sleep, never a
        render. Left to TaskRunner it rendered in bpy, from every thread at once (bpy initialised twice: the
        process died)."""
        return self._sleep(t), f"{t.id}".encode()

    def _sleep(self, t: Claimed) -> str:
        # `slept` adds up over a message (a whole view sleeps its render and every derivation); the caller
        # resets it
        s = self.task_s * self.rng.uniform(0.8, 1.2) if self.task_s > 0 else task_seconds(t.cue, self.rng)
        self.slept += s
        if self.killed.wait(s):
            raise Killed(t.id)
        return f"sim/{t.job_id}/{t.cue}/{t.point}_{t.view}"


def task_id_of(raw: bytes) -> int:
    """The task id in a Celery protocol-2 message as kombu stores it in Redis (base64 JSON body)."""
    env = json.loads(raw)
    return int(json.loads(base64.b64decode(env["body"]))[0][0])


def worker_process(
    index: int, n_workers: int, settings: Settings, redis_url: str, task_s: float, kill_ids: list[str],
    kill_at: Any, stop: Any, out: Any, measuring: Any, nice: int = 0, probe: bool = False,
) -> None:
    """`n_workers` simulated workers (threads) sharing one connection pool; reports stats into `out`.

    `nice` lowers the process's CPU priority: a real fleet runs on other machines, so the host's orchestrator
    (scheduler, Postgres, Redis, API) should not queue behind the simulation's threads for CPU. A `probe` is
    one worker alone in its process at normal priority, as a real worker process is: its task overhead is what
    a worker of the fleet would see, without the harness's hundreds of threads per interpreter.
    """
    import os

    import redis

    if nice:
        os.nice(nice)
    engine = worker_engine(
        settings.database_url, pool_size=POOL_PER_PROCESS, max_overflow=0, pool_timeout=120
    )
    sm = make_sessionmaker(engine)
    store = LocalStore(settings.data_dir / "objects")
    queues = [settings.queue_render, settings.queue_derive]
    lock = threading.Lock()
    stats: dict[str, Any] = {"done": 0, "skipped": 0, "killed": [], "beat_s": [], "overhead_s": [],
                             "message_overhead_s": [], "probe": probe}
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
            wall = time.perf_counter() - t - runner.slept  # claims + records, not the work
            done = sum(o.status == "done" for o in (outcome, *outcome.batch))
            with lock:
                stats["done"] += done
                stats["skipped"] += outcome.status != "done"
                if measuring.is_set() and done:  # in the measured window only
                    # a whole view is one message for ~19 tasks: its overhead shared by them (once per task)
                    stats["message_overhead_s"].append(wall)
                    stats["overhead_s"].extend([wall / done] * done)
        r.close()

    def drive_heartbeats() -> None:
        # Each worker beats every interval, spread evenly over the interval (real workers start at random
        # times).
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
                        if measuring.is_set():
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
    helpers = [
        threading.Thread(target=drive_heartbeats, daemon=True),
        threading.Thread(target=watch_kill, daemon=True),
    ]
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
    """The real Scheduler loop (plan, dispatch, reap, complete) with the synthetic plan; reports its
    counts."""
    from bench.scale.fanout import plan_is
    from services.scheduler.celery_transport import CeleryTransport
    from services.scheduler.compaction import Compactor
    from services.scheduler.loop import Scheduler

    engine = make_engine(settings.database_url, pool_size=2)
    transport = CountingTransport(CeleryTransport(settings=settings))
    plan_is(plan)  # this process's planner
    sched = Scheduler(
        make_sessionmaker(engine), LocalStore(settings.data_dir / "objects"), transport, settings,
        "sim-scheduler", cache_dir=settings.data_dir / "cache",
    )
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

    compacted: dict[str, Any] = {"views": 0, "tasks": 0, "passes": [], "cpu_s": 0.0}
    compactor = sched.compactor

    def counted_compaction() -> Any:
        assert compactor is not None
        # the tick's thread: the scheduler's own CPU in compaction (its backend's is not split)
        c = time.thread_time()
        res = Compactor.run_once(compactor)
        compacted["cpu_s"] += time.thread_time() - c
        compacted["views"] += res.views
        compacted["tasks"] += res.tasks
        compacted["passes"].append(res.seconds)
        return res

    if compactor is not None:
        compactor.run_once = counted_compaction  # type: ignore[method-assign]
    sched.dispatch_once = timed_dispatch  # type: ignore[method-assign]
    sched.reap_once = counted_reap  # type: ignore[method-assign]
    sched.run_forever(stop, interval=0.2)
    out.put({"sent": transport.sent, "send_s": transport.send_s, "passes": passes, "reaped": reaped,
             "compacted_views": compacted["views"], "compacted_tasks": compacted["tasks"],
             "compact_passes": compacted["passes"], "compact_cpu_s": compacted["cpu_s"]})
    transport.inner.close()
    engine.dispose()


class _NoStore:
    """An object store that keeps nothing (the isolated overhead measures the database round trips only)."""

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> Any:
        import hashlib

        from services.core.storage.base import ObjectInfo

        return ObjectInfo(key, len(data), hashlib.sha256(data).hexdigest())


def isolated_overhead(db_url: str, settings: Settings, task_ids: list[int]) -> tuple[list[float], float]:
    """Seconds of claim + record done per task for one worker alone (no sleep, nothing stored), and the CPU
    milliseconds per task of its Postgres backend: the task overhead without the simulation's own contention
    (hundreds of threads per process sharing six connections)."""
    from sqlalchemy import text

    from bench.lib.scale_cost import cpu_seconds

    engine = worker_engine(db_url, pool_size=1)
    sm = make_sessionmaker(engine)
    runner = SleepingRunner(sm, _NoStore(), settings, "alone",  # type: ignore[arg-type]
                            task_s=1e-6, killed=threading.Event())
    with sm() as s:
        backend = int(s.scalar(text("SELECT pg_backend_pid()")) or 0)
    cpu0 = cpu_seconds(backend)
    out: list[float] = []
    for tid in task_ids:
        t = time.perf_counter()
        runner.slept = 0.0
        outcome = runner.run(tid)
        wall = time.perf_counter() - t - runner.slept
        done = sum(o.status == "done" for o in (outcome, *outcome.batch))
        # a task an earlier view batch of this list took is skipped (no claim); a batch's overhead is shared
        assert done or outcome.status == "skipped", outcome
        out.extend([wall / done] * done if done else [])
    pg_ms = 1000 * (cpu_seconds(backend) - cpu0) / max(len(out), 1)
    engine.dispose()
    return out, pg_ms
