"""Chaos soak (DESIGN.md section 7, issue 11 item 16): several jobs run on a real deployment while workers are
killed with kill -9 at random (and replaced), the scheduler is killed and restarted, and Redis and Postgres
connections are dropped under the services. Afterwards every job is done, every output is present exactly
once with a matching sha256, no task is left queued or running, and each killed worker's task ran again.

Bounded: about CHAOS_S seconds of faults, then the jobs must finish within SETTLE_S. The figures (run length,
faults, jobs and tasks completed, recovery time after each kill -9) are printed (`pytest -s` shows them).
"""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import time
from collections import Counter
from datetime import datetime
from pathlib import Path
from urllib.parse import urlparse

import pytest
import redis
from sqlalchemy import func, select

from services.core.db.models import Job, Task, utcnow
from tests.e2e.conftest import REDIS_DB_URL, SCHEDULER_APP, WORKER_APP, Cluster, Proc
from tests.e2e.test_distributed import assert_exactly_once, submit_direct, wait, write_spec

pytestmark = pytest.mark.slow

CHAOS_S = 50.0  # seconds of fault injection
FAULTS = ["kill_worker"] * 4 + ["kill_scheduler", "drop_postgres", "drop_redis"] * 2  # injected in random order
SETTLE_S = 120.0  # then every job must be done within this
N_WORKERS = 3
# Short enough for a bounded run, in the same order as the deployment's defaults: a worker is declared
# dead after 6 s without a heartbeat (its task comes back then), leases and the lost-message timeout are 20 s.
CHAOS_ENV = {"OMNIDATA_LEASE_S": "20", "OMNIDATA_HEARTBEAT_TIMEOUT_S": "6", "OMNIDATA_DISPATCH_WINDOW": "8"}
SPEC = """
cameras: {{mode: object, object_count: 6}}
points: {{count: 4, min_views: 2, max_views: 2}}
views: {{resolution: 32}}
cues: [rgb, normal, depth_zbuffer, edge_texture, point_info, segment_unsup2d]
seed: {seed}
"""
BUNNY = "stanford_bunny/bun_zipper_res2.ply"
JOBS = [("ycb_banana", 1), (BUNNY, 2), ("ycb_banana", 3), (BUNNY, 4), ("ycb_banana", 5), (BUNNY, 6)]  # (scene, seed)


def held_tasks(cluster: Cluster, proc: Proc) -> list[int]:
    """Tasks the worker is running now (its id is its --hostname, name@host)."""
    worker_id = f"{proc.name}@{socket.gethostname()}"
    with cluster.sm() as s:
        return [int(i) for (i,) in s.execute(select(Task.id).where(Task.state == "running", Task.worker_id == worker_id))]


def kill_9(cluster: Cluster, proc: Proc, patience_s: float = 3.0) -> list[int]:
    """kill -9 a worker, preferably frozen mid-task (tried for `patience_s`); returns the tasks it held."""
    deadline = time.monotonic() + patience_s
    while True:
        os.killpg(proc.popen.pid, signal.SIGSTOP)
        held = held_tasks(cluster, proc)
        if held or time.monotonic() > deadline:
            break
        os.killpg(proc.popen.pid, signal.SIGCONT)
        time.sleep(0.05)
    proc.stop(signal.SIGKILL)
    return held


def drop_redis_clients(url: str) -> int:
    """CLIENT KILL every connection to this deployment's Redis database (workers' consumers, the scheduler)."""
    db = int(urlparse(url).path.lstrip("/") or 0)
    r = redis.Redis.from_url(url)
    try:
        me = r.client_id()
        victims = [c["id"] for c in r.client_list() if int(c.get("db", -1)) == db and int(c["id"]) != me]
        for cid in victims:
            r.client_kill_filter(_id=cid)
        return len(victims)
    finally:
        r.close()


def test_chaos_soak(cluster: Cluster, scenes_dir: Path, tmp_path: Path) -> None:
    rng = random.Random(11)
    for p in cluster.procs:  # restart the fixture's services with the chaos settings
        p.stop()
    scheduler = cluster.start_scheduler(**CHAOS_ENV)
    workers = [cluster.start_worker(f"worker-{k}", **CHAOS_ENV) for k in range(N_WORKERS)]
    t_start = time.monotonic()
    job_ids = [submit_direct(cluster, scenes_dir / scene, write_spec(tmp_path, SPEC.format(seed=seed)))
               for scene, seed in JOBS]

    def running() -> bool:
        with cluster.sm() as s:
            return s.scalar(select(func.count()).select_from(Job).where(Job.state == "running")) > 0

    wait(running, 120, "a job to be planned", cluster)
    faults: Counter[str] = Counter()
    kills: list[tuple[datetime, list[int]]] = []  # (when, tasks the worker held)
    schedule = FAULTS.copy()
    rng.shuffle(schedule)
    n_worker = N_WORKERS
    for fault in schedule:  # at random moments, about CHAOS_S / len(FAULTS) apart
        time.sleep(rng.uniform(0.5, 1.5) * CHAOS_S / len(schedule))
        if fault == "kill_worker":
            victim = rng.choice([w for w in workers if w.alive()])
            when = utcnow()
            kills.append((when, kill_9(cluster, victim)))
            workers.remove(victim)
            workers.append(cluster.start_worker(f"worker-{n_worker}", **CHAOS_ENV))  # as an orchestrator would
            n_worker += 1
        elif fault == "kill_scheduler":
            scheduler.stop(signal.SIGKILL)
            scheduler = cluster.start_scheduler(**CHAOS_ENV)
        elif fault == "drop_postgres":
            cluster.terminate_connections(WORKER_APP)
            cluster.terminate_connections(SCHEDULER_APP)
        else:
            drop_redis_clients(REDIS_DB_URL)
        faults[fault] += 1
    chaos_s = time.monotonic() - t_start

    def all_final() -> bool:
        with cluster.sm() as s:
            states = set(s.scalars(select(Job.state).where(Job.id.in_(job_ids))))
            return states <= {"done", "failed", "cancelled"}

    wait(all_final, SETTLE_S, "every job to finish after the chaos", cluster)
    run_s = time.monotonic() - t_start
    with cluster.sm() as s:
        jobs = {j.id: (j.state, j.error) for j in s.scalars(select(Job).where(Job.id.in_(job_ids)))}
    assert all(state == "done" for state, _ in jobs.values()), f"{jobs}\n{cluster.logs()}"
    outputs = sum(sum(len(e["outputs"]) for e in assert_exactly_once(cluster, j)) for j in job_ids)
    assert all(p.alive() for p in [scheduler, *workers]), cluster.logs()

    held = [t for _, ids in kills for t in ids]
    with cluster.sm() as s:
        tasks = s.scalar(select(func.count()).select_from(Task).where(Task.job_id.in_(job_ids)))
        first, last = s.execute(select(func.min(Job.created_at), func.max(Job.finished_at)).where(Job.id.in_(job_ids))).one()
        rerun = {int(r.id): r for r in s.execute(
            select(Task.id, Task.attempts, Task.finished_at).where(Task.id.in_(held)))}
    assert held, "no worker was killed mid-task"
    assert all(r.attempts >= 2 for r in rerun.values()), rerun  # each killed worker's task was reaped and rerun
    recovery = [(rerun[t].finished_at - when).total_seconds() for when, ids in kills for t in ids]
    figures = {
        "run_s": round(run_s, 1), "chaos_s": round(chaos_s, 1), "workload_s": round((last - first).total_seconds(), 1),
        "faults": dict(faults),
        "faults_total": sum(faults.values()), "jobs_done": len(jobs), "tasks_done": int(tasks or 0),
        "outputs_once_sha256_ok": outputs, "killed_mid_task": len(held),
        "recovery_after_kill9_s": {"max": round(max(recovery), 1), "mean": round(sum(recovery) / len(recovery), 1)}
        if recovery else None,
    }
    print("\nchaos soak:", json.dumps(figures))
