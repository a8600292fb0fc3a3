"""Chaos soak (DESIGN.md section 7, issue 11 item 16): several jobs run on a real deployment while workers are
killed with kill -9 at random (and replaced), the scheduler is killed and restarted, Redis and Postgres
connections are dropped under the services, and the S3 endpoint answers 503 for a few seconds (issue 51).
Afterwards every job is done, every output is present exactly once with a matching sha256, no task is left
queued or running, and each killed worker's task ran again.

Bounded: about CHAOS_S seconds of faults, then the jobs must finish within SETTLE_S. The figures (run length,
faults, jobs and tasks completed, recovery time after each kill -9) are printed (`pytest -s` shows them).
"""

from __future__ import annotations

import base64
import json
import os
import random
import signal
import socket
import time
from collections import Counter
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest
import redis
from sqlalchemy import func, select

from services.core.db.compacted import compacted_tasks
from services.core.db.models import Job, Task, utcnow
from tests.conftest import S3Server
from tests.e2e.conftest import REDIS_DB_URL, SCHEDULER_APP, WORKER_APP, Cluster, Proc
from tests.e2e.test_distributed import assert_exactly_once, submit_direct_together, wait, write_spec
from tests.fixtures.holding_proxy import HoldingProxy

pytestmark = [pytest.mark.slow, pytest.mark.alone]

CHAOS_S = 40.0  # seconds of fault injection; the workload is topped up while it runs (TOP_UP_BELOW)
# injected in random order; store_503: the S3 endpoint answers the deployment's writes 503 for STORE_OUTAGE_S
FAULTS = ["kill_worker"] * 8 + ["kill_scheduler", "drop_postgres", "drop_redis", "store_503"] * 2
STORE_OUTAGE_S = 3.0
SETTLE_S = 120.0  # then every job must be done within this
N_WORKERS = 3
# A worker is declared dead after 6 s without a heartbeat (its running task comes back then, and the messages
# it may have reserved are sent again); leases and the lost-message timeout are 120 s, longer than the
# promised recovery (heartbeat timeout + 30 s), so they cannot be what meets it. Workers reserve 2 messages
# each, so a kill often lands on a worker holding a reserved message.
HEARTBEAT_TIMEOUT_S = 6
# finished views are compacted at once (services.scheduler.compaction), so the faults land on compacted views
# too
CHAOS_ENV = {
    "OMNIDATA_LEASE_S": "120", "OMNIDATA_HEARTBEAT_TIMEOUT_S": str(HEARTBEAT_TIMEOUT_S),
    "OMNIDATA_DISPATCH_WINDOW": "8", "OMNIDATA_WORKER_PREFETCH": "2", "OMNIDATA_COMPACT_AFTER_S": "0",
}
# the soak appends its figures to this file when set (bench/results/chaos.json to record a run); a test run
# leaves the checkout as it found it
RESULTS_ENV = "OMNIDATA_CHAOS_RESULTS"
SPEC = """
cameras: {{mode: object, object_count: 6}}
points: {{count: 4, min_views: 2, max_views: 2}}
views: {{resolution: 32}}
cues: [rgb, normal, depth_zbuffer, edge_texture, point_info, segment_unsup2d]
seed: {seed}
max_attempts: 6
"""
# max_attempts: each fault that stops a worker mid-task costs its tasks an attempt. With 14 faults in 40 s on
# 3 workers a task can meet 3 (a CI run had one caught by two kills, then by a heartbeat cut off by a dropped
# Postgres connection), which the default of 3 turns into a failed job. The soak tests recovery, not the
# attempt limit. A job is added whenever fewer than this many are unfinished before a fault, so every fault
# lands on pending work whatever the machine's speed (the six jobs took ~80 s on a loaded host, ~22 s on an
# idle one: kills then found every worker idle).
TOP_UP_BELOW = 2
BUNNY = "stanford_bunny/bun_zipper_res2.ply"
# (scene, seed)
JOBS = [("ycb_banana", 1), (BUNNY, 2), ("ycb_banana", 3), (BUNNY, 4), ("ycb_banana", 5), (BUNNY, 6)]


def held_tasks(cluster: Cluster, proc: Proc) -> list[int]:
    """Tasks the worker is running now (its id is its --hostname, name@host)."""
    worker_id = f"{proc.name}@{socket.gethostname()}"
    with cluster.sm() as s:
        return [
            int(i)
            for (i,) in s.execute(select(Task.id).where(Task.state == "running", Task.worker_id == worker_id))
        ]


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
    # A result the worker sent just before it froze still lands (its statement runs on in Postgres): such a
    # task is done, not orphaned. The tasks it left running are the ones the recovery must rerun.
    time.sleep(0.5)
    still = set(held_tasks(cluster, proc))
    return [t for t in held if t in still]


def unacked_queued(cluster: Cluster) -> list[int]:
    """Tasks still queued whose message Redis holds as delivered to some worker but not acknowledged."""
    r = redis.Redis.from_url(REDIS_DB_URL)
    try:
        ids = [
            int(json.loads(base64.b64decode(json.loads(raw)[0]["body"]))[0][0]) for raw in r.hvals("unacked")
        ]
    finally:
        r.close()
    with cluster.sm() as s:
        return [int(i) for i in s.scalars(select(Task.id).where(Task.id.in_(ids), Task.state == "queued"))]


def drop_redis_clients(url: str) -> int:
    """CLIENT KILL every connection to this deployment's Redis database (workers' consumers, the
    scheduler)."""
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


def store_outage(cluster: Cluster, proxy: HoldingProxy, bucket: str) -> float | None:
    """The S3 endpoint answers the deployment's writes 503 for STORE_OUTAGE_S, then recovers; returns the
    seconds from its recovery until no job waits for the store any more (None: no job was held)."""
    proxy.fail(f"PUT /{bucket}/{cluster.prefix}/".encode())
    time.sleep(STORE_OUTAGE_S)

    def held() -> int:
        with cluster.sm() as s:
            return int(s.scalar(select(func.count()).select_from(Job).where(Job.paused_by == "storage")) or 0)

    was_held = held() > 0
    proxy.fail()
    recovered = time.monotonic()
    wait(lambda: held() == 0, 60, "the jobs held for the store to resume", cluster)
    return round(time.monotonic() - recovered, 1) if was_held else None


@pytest.fixture()
def s3_proxy(s3_server: S3Server) -> Iterator[HoldingProxy]:
    """A proxy the scheduler and the workers reach S3 through (store_503 makes it answer 503 a while)."""
    proxy = HoldingProxy(s3_server.endpoint_url)
    try:
        yield proxy
    finally:
        proxy.close()


def test_chaos_soak(bare_cluster: Cluster, scenes_dir: Path, tmp_path: Path, s3_proxy: HoldingProxy,
                    s3_server: S3Server) -> None:
    cluster = bare_cluster
    rng = random.Random(11)
    env = {**CHAOS_ENV, "OMNIDATA_S3_ENDPOINT_URL": s3_proxy.url}
    scheduler = cluster.start_scheduler(**env)
    workers = [cluster.start_worker(f"worker-{k}", **env) for k in range(N_WORKERS)]
    store_resumed: list[float | None] = []  # per store_503: seconds from its recovery to no job held
    t_start = time.monotonic()
    jobs = [
        (scenes_dir / scene, write_spec(tmp_path, SPEC.format(seed=seed), f"seed{seed}"))
        for scene, seed in JOBS
    ]
    # the first job of each space registers it; the rest reuse it
    job_ids = submit_direct_together(cluster, jobs[:2]) + submit_direct_together(cluster, jobs[2:])

    def running() -> bool:
        with cluster.sm() as s:
            return s.scalar(select(func.count()).select_from(Job).where(Job.state == "running")) > 0

    wait(running, 120, "a job to be planned", cluster)
    faults: Counter[str] = Counter()
    kills: list[tuple[datetime, list[int]]] = []  # (when, tasks the worker held)
    reserved: list[list[int]] = []  # per kill: tasks queued whose message was reserved by some worker
    schedule = FAULTS.copy()
    rng.shuffle(schedule)
    n_worker = N_WORKERS
    top_up_seeds = iter(range(100, 200))

    def unfinished() -> int:
        with cluster.sm() as s:
            return int(s.scalar(select(func.count()).select_from(Job).where(
                Job.id.in_(job_ids), Job.state.not_in(["done", "failed", "cancelled"]))) or 0)

    for fault in schedule:  # at random moments, about CHAOS_S / len(FAULTS) apart
        time.sleep(rng.uniform(0.5, 1.5) * CHAOS_S / len(schedule))
        if unfinished() < TOP_UP_BELOW:
            seed = next(top_up_seeds)
            spec = write_spec(tmp_path, SPEC.format(seed=seed), f"seed{seed}")
            job_ids += submit_direct_together(cluster, [(scenes_dir / "ycb_banana", spec)])
            wait(running, 120, "a topped-up job to be planned", cluster)
        if fault == "kill_worker":
            victim = rng.choice([w for w in workers if w.alive()])
            held_by_victim = kill_9(cluster, victim)
            kills.append((utcnow(), held_by_victim))
            reserved.append(unacked_queued(cluster))
            workers.remove(victim)
            workers.append(cluster.start_worker(f"worker-{n_worker}", **env))  # as an orchestrator would
            n_worker += 1
        elif fault == "kill_scheduler":
            scheduler.stop(signal.SIGKILL)
            scheduler = cluster.start_scheduler(**env)
        elif fault == "store_503":
            store_resumed.append(store_outage(cluster, s3_proxy, s3_server.bucket))
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
    dead = [f"{p.name} (exit {p.popen.returncode})" for p in [scheduler, *workers] if not p.alive()]
    assert not dead, f"{dead}\n{cluster.logs()}"

    held = [t for _, ids in kills for t in ids]
    with cluster.sm() as s:
        tasks = s.scalar(select(func.count()).select_from(Task).where(Task.job_id.in_(job_ids)))
        first, last = s.execute(
            select(func.min(Job.created_at), func.max(Job.finished_at)).where(Job.id.in_(job_ids))
        ).one()
        wanted = set(held + [t for r in reserved for t in r])
        rerun: dict[int, Any] = {int(r.id): r for r in s.execute(
            select(Task.id, Task.attempts, Task.finished_at).where(Task.id.in_(wanted)))}
        # compacted views keep ids too
        packed = [t for j in job_ids for t in compacted_tasks(s, s.get(Job, j))]
        rerun.update({t.id: t for t in packed if t.id in wanted})
        tasks += len(packed)
    assert packed, "no view was compacted during the chaos (OMNIDATA_COMPACT_AFTER_S=0)"
    assert held, "no worker was killed mid-task"
    assert all(rerun[t].attempts >= 2 for t in held), rerun  # each killed worker's task was reaped and rerun
    # A kill's recovery: from the kill to the last of the tasks it interrupted (running on the victim, or
    # queued with a reserved message, possibly the victim's) being done. A task caught again by a later kill
    # (its message was reserved by a worker killed next) counts for that later kill, the last fault that held
    # it up.
    recovery = []
    later: set[int] = set()
    for (when, ids), res in reversed(list(zip(kills, reserved, strict=True))):
        mine = {*ids, *res} - later
        later |= {*ids, *res}
        if mine:
            recovery.append(max((rerun[t].finished_at - when).total_seconds() for t in mine))
    recovery.reverse()
    figures = {
        "run_s": round(run_s, 1), "chaos_s": round(chaos_s, 1),
        "workload_s": round((last - first).total_seconds(), 1), "faults": dict(faults),
        "compacted_tasks": len(packed), "faults_total": sum(faults.values()), "jobs_done": len(jobs),
        "tasks_done": int(tasks or 0), "outputs_once_sha256_ok": outputs, "killed_mid_task": len(held),
        "reserved_at_kill": sum(len(r) for r in reserved),
        "recovery_after_kill9_s": {"worst": round(max(recovery), 1), "each": [round(x, 1) for x in recovery]},
        "kills_that_interrupted_work": len(recovery),
        "store_503_s": STORE_OUTAGE_S, "store_503_resumed_after_s": store_resumed,
        "bound_s": HEARTBEAT_TIMEOUT_S + 30,
        "note": "2-core machine shared with other developers' work",
    }
    print("\nchaos soak:", json.dumps(figures))
    results = Path(os.environ.get(RESULTS_ENV) or tmp_path / "chaos.json")
    runs = json.loads(results.read_text()) if results.exists() else []
    results.write_text(
        json.dumps([*runs, {"at": utcnow().isoformat(timespec="seconds"), **figures}], indent=1) + "\n"
    )
    # the promise, for the worst kill, not the mean
    assert max(recovery) <= HEARTBEAT_TIMEOUT_S + 30, recovery
