"""End to end on a real deployment (API, scheduler, two Celery workers, Postgres, Redis, S3 over HTTP), and
the faults DESIGN.md section 7 names: kill -9 of a worker, a Redis restart and dropped Postgres connections
mid-job. Each time the job must complete with every output present exactly once and no task left running.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import func, select
from sqlalchemy.engine import make_url

from services.core.db.compacted import compacted_tasks
from services.core.db.counters import job_progress
from services.core.db.models import Job, Task
from services.core.domain.cues import CATALOG
from tests.conftest import GeneratedRun
from tests.e2e.conftest import (
    REPO,
    SCHEDULER_APP,
    WORKER_APP,
    Cluster,
    Proc,
    free_port,
    start_redis,
    stop_redis,
)
from tests.fixtures.cli import WIDE
from tests.fixtures.holding_proxy import HoldingProxy

pytestmark = pytest.mark.slow

# Long enough (18 views) that a fault injected after the first outputs still finds the job running: a worker
# runs a whole view at once, so a 9-view job could finish within a second of its first outputs.
FAULTS = """
cameras: {mode: object, object_count: 8}
points: {count: 6, min_views: 3, max_views: 3}
views: {resolution: 64}
cues: [rgb, normal, depth_zbuffer, edge_texture, point_info, segment_unsup2d]
"""


def write_spec(tmp_path: Path, text: str, name: str = "job") -> Path:
    p = tmp_path / f"{name}.yaml"
    p.write_text(text)
    return p


def submit(
    cluster: Cluster, space: Path, spec: Path, *extra: str, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "submit", str(space), "--spec", str(spec), *extra], cwd=REPO,
        env=cluster.env, capture_output=True, text=True, timeout=timeout,
    )


def submit_direct(cluster: Cluster, space: Path, spec: Path) -> int:
    """`omnidata submit` without an API: registers the space and creates the job in the database."""
    res = submit(cluster, space, spec, "--no-follow", "--direct")
    assert res.returncode == 0, res.stderr
    return int(res.stdout.strip().splitlines()[-1])


def submit_direct_together(cluster: Cluster, jobs: list[tuple[Path, Path]]) -> list[int]:
    """`submit_direct` of several (space, spec) at once, each in its own process; returns the job ids in
    order. Jobs of one space must not be in one call: two processes registering the same space would race."""
    procs = [
        subprocess.Popen(
            [
                sys.executable, "-m", "services.cli", "submit", str(space), "--spec", str(spec),
                "--no-follow", "--direct",
            ],
            cwd=REPO, env=cluster.env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        )
        for space, spec in jobs
    ]
    ids = []
    for p in procs:
        out, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
        ids.append(int(out.strip().splitlines()[-1]))
    return ids


def done_count(cluster: Cluster, job_id: int) -> int:
    with cluster.sm() as s:
        return int(job_progress(s, job_id).get("rgb", {}).get("done", 0))


def wait(cond, timeout: float, what: str, cluster: Cluster) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n{cluster.logs()}")
        time.sleep(0.1)


def job_state(cluster: Cluster, job_id: int) -> str:
    with cluster.sm() as s:
        job = s.get(Job, job_id)
        return job.state if job is not None else "missing"


def wait_done(cluster: Cluster, job_id: int, timeout: float) -> None:
    def final() -> bool:
        with cluster.sm() as s:
            job = s.get(Job, job_id)
            return job is not None and job.state in ("done", "failed", "cancelled")

    wait(final, timeout, f"job {job_id} to finish", cluster)
    with cluster.sm() as s:
        job = s.get(Job, job_id)
        assert job.state == "done", f"{job.state}: {job.error}\n{cluster.logs()}"


def assert_exactly_once(cluster: Cluster, job_id: int) -> list[dict]:
    """Every task done once, counters exact, and the store holds exactly the manifest's outputs (sha256
    ok)."""
    with cluster.sm() as s:
        truth: dict[str, dict[str, int]] = {}
        for cue, state, n in s.execute(select(Task.cue, Task.state, func.count()).where(Task.job_id == job_id)
                                       .group_by(Task.cue, Task.state)):
            truth.setdefault(cue, {})[state] = int(n)
        job = s.get(Job, job_id)
        packed = compacted_tasks(s, job)  # views compacted once finished (services.scheduler.compaction)
        for t in packed:
            per = truth.setdefault(t.cue, {})
            per["done"] = per.get("done", 0) + 1
        assert job_progress(s, job_id) == truth
        # nothing running, queued, failed
        assert {st for states in truth.values() for st in states} == {"done"}
        root = job.output_root
        internal = [n for n, c in CATALOG.items() if c.internal]
        keys = [
            k
            for (k,) in s.execute(
                select(Task.output_key).where(Task.job_id == job_id, Task.cue.not_in(internal))
            )
        ]
        keys += [t.output_key for t in packed if t.cue not in internal]
    assert len(keys) == len(set(keys))
    manifest = [
        json.loads(line) for line in cluster.store.get_bytes(f"{root}/manifest.jsonl").decode().splitlines()
    ]
    outputs = {f"{root}/{o['key']}": o for e in manifest for o in e["outputs"].values()}
    assert set(outputs) == set(keys)
    stored = {k for k in cluster.store.list(f"{root}/") if not k.startswith(f"{root}/_plan/")}
    assert stored == set(outputs) | {f"{root}/manifest.jsonl", f"{root}/job.json"}  # no pass cache, no extras
    for key, o in outputs.items():
        assert hashlib.sha256(cluster.store.get_bytes(key)).hexdigest() == o["sha256"], key
    return manifest


def differing_outputs(service: list[dict], local: list[dict], service_bytes: Callable[[str], bytes],
                      generated: Path) -> str:
    """Each output whose record differs between the two manifests: both sizes and, for images, the pixels that
    differ and by how much (an intermittent mismatch is diagnosed from the CI log alone)."""
    lines = []
    for ours, theirs in zip(service, local, strict=False):
        for cue, out in ours["outputs"].items():
            other = theirs["outputs"].get(cue)
            if out == other:
                continue
            line = (
                f"{out['key']}: service {out.get('size')} bytes, generate {other and other.get('size')} bytes"
            )
            if other and out["key"].endswith(".png"):
                a = np.asarray(Image.open(io.BytesIO(service_bytes(out["key"]))), dtype=np.int64)
                b = np.asarray(Image.open(generated / other["key"]), dtype=np.int64)
                if a.shape == b.shape:
                    line += (
                        f"; {int((a != b).any(axis=-1).sum() if a.ndim == 3 else (a != b).sum())} "
                        f"pixels differ, by up to {int(np.abs(a - b).max())}"
                    )
            lines.append(line)
    return "\n".join(lines or [f"{len(service)} records against {len(local)}"])


def test_job_over_the_api_completes_and_matches_generate(
    cluster: Cluster, tiny_banana: GeneratedRun, scenes_dir, tmp_path
):
    # what the embedded `omnidata generate` wrote for the same spec, seed and name
    generated = tiny_banana.out
    url = cluster.start_api()
    spec = write_spec(tmp_path, WIDE)
    res = submit(cluster, scenes_dir / "ycb_banana", spec, "--seed", "7", "--name", "tiny", "--api", url,
                 "--token", cluster.token, "--interval", "0.5", timeout=300)
    assert res.returncode == 0, res.stderr + cluster.logs()
    job_id = int(res.stdout.strip().splitlines()[-1])
    assert f"job {job_id} done" in res.stderr
    manifest = assert_exactly_once(cluster, job_id)
    local = [json.loads(line) for line in (generated / "manifest.jsonl").read_text().splitlines()]
    root = f"jobs/{job_id}"
    # same keys, sizes and sha256: the service and the embedded mode agree (else: which files, and by how
    # much)
    assert manifest == local, differing_outputs(
        manifest, local, lambda key: cluster.store.get_bytes(f"{root}/{key}"), generated
    )
    for key in ("rgb/tiny/ycb_banana/point_0_view_0_domain_rgb.png",
                "fragments/tiny/ycb_banana/point_1_view_1_domain_fragments.npy",
                "position/tiny/ycb_banana/point_1_view_0_domain_position.exr"):
        assert cluster.store.get_bytes(f"{root}/{key}") == (generated / key).read_bytes()
    job_doc = json.loads(cluster.store.get_bytes(f"{root}/job.json"))
    assert job_doc["spec"] == json.loads((generated / "job.json").read_text())["spec"]


def kill_9_mid_task(cluster: Cluster, victim: Proc, job_id: int) -> tuple[list[int], list[str]]:
    """kill -9 the victim (Celery parent and pool child) while it runs a task; returns (its tasks, its worker
    ids)."""
    victim_ids = [f"{victim.name}@{socket.gethostname()}"]  # its --hostname, kept by every pool child

    def victim_running() -> list[int]:
        with cluster.sm() as s:
            return [int(i) for (i,) in s.execute(select(Task.id).where(
                Task.job_id == job_id, Task.state == "running", Task.worker_id.in_(victim_ids)))]

    # Freeze the victim, and kill it only when frozen in the middle of a task (tasks take milliseconds).
    deadline = time.monotonic() + 60
    while True:
        os.killpg(victim.popen.pid, signal.SIGSTOP)
        held = victim_running()
        if held:
            break
        os.killpg(victim.popen.pid, signal.SIGCONT)
        assert time.monotonic() < deadline, "the victim never ran a task\n" + cluster.logs()
        time.sleep(0.03)
    victim.stop(signal.SIGKILL)
    assert not victim.alive()
    return held, victim_ids


def assert_rerun_elsewhere(cluster: Cluster, held: list[int], victim_ids: list[str]) -> None:
    with cluster.sm() as s:
        rows = s.execute(select(Task.id, Task.attempts, Task.worker_id).where(Task.id.in_(held))).all()
    # reaped, rerun
    assert held and all(r.attempts >= 2 and r.worker_id not in victim_ids for r in rows), rows


@pytest.mark.alone
def test_kill_9_of_a_worker_mid_task_is_rerun_at_the_heartbeat_timeout_not_the_lease(bare_cluster: Cluster,
                                                                                    scenes_dir, tmp_path):
    # The deployment's defaults: 300 s leases, workers declared dead after 30 s without a heartbeat. One run
    # for what used to be two (a kill -9 under 10 s leases, and this): lease expiry itself is tested in
    # tests/scheduler/test_reaper.py.
    cluster = bare_cluster
    defaults = {"OMNIDATA_LEASE_S": "300", "OMNIDATA_HEARTBEAT_TIMEOUT_S": "30"}
    cluster.start_scheduler(**defaults)
    workers = [cluster.start_worker(f"worker-{n}-300", **defaults) for n in ("a", "b")]
    job_id = submit_direct(cluster, scenes_dir / "ycb_banana", write_spec(tmp_path, FAULTS))
    wait(lambda: done_count(cluster, job_id) >= 2, 120, "first outputs", cluster)
    held, victim_ids = kill_9_mid_task(cluster, workers[0], job_id)
    killed_at = time.monotonic()
    wait_done(cluster, job_id, 90)  # DESIGN section 7: a small job finishes within 90 s of a kill -9
    print(
        f"\njob done {time.monotonic() - killed_at:.1f} s after the kill -9 (lease 300 s, heartbeat "
        "timeout 30 s)"
    )
    assert_exactly_once(cluster, job_id)
    assert_rerun_elsewhere(cluster, held, victim_ids)


def test_redis_restart_mid_job(own_redis: int, bare_cluster: Cluster, scenes_dir, tmp_path):
    cluster = bare_cluster
    broker = {"OMNIDATA_BROKER_URL": f"redis://127.0.0.1:{own_redis}/0"}
    cluster.start_scheduler(**broker)
    for name in ("worker-a", "worker-b"):
        cluster.start_worker(name, **broker)
    job_id = submit_direct(cluster, scenes_dir / "ycb_banana", write_spec(tmp_path, FAULTS))
    wait(lambda: done_count(cluster, job_id) >= 2, 120, "first outputs", cluster)
    stop_redis(own_redis)  # every queued message is gone; workers and scheduler must reconnect
    time.sleep(1.0)  # they notice the broker is gone
    start_redis(own_redis, tmp_path / "redis")
    assert job_state(cluster, job_id) == "running"  # the fault hit the job mid-way
    wait_done(cluster, job_id, 180)
    assert_exactly_once(cluster, job_id)
    assert all(p.alive() for p in cluster.procs)


def test_postgres_connections_dropped_mid_job(cluster: Cluster, scenes_dir, tmp_path):
    job_id = submit_direct(cluster, scenes_dir / "ycb_banana", write_spec(tmp_path, FAULTS))
    wait(lambda: done_count(cluster, job_id) >= 2, 120, "first outputs", cluster)
    killed = cluster.terminate_connections(WORKER_APP)
    assert killed >= 2  # each worker holds connections (task runner, heartbeat)
    cluster.terminate_connections(SCHEDULER_APP)
    assert job_state(cluster, job_id) == "running"  # the fault hit the job mid-way
    time.sleep(1.0)
    cluster.terminate_connections(WORKER_APP)  # again, while they reconnect
    assert job_state(cluster, job_id) in ("running", "done")  # the drops failed nothing
    wait_done(cluster, job_id, 180)
    assert_exactly_once(cluster, job_id)
    assert all(p.alive() for p in cluster.procs)



def test_services_started_while_the_database_does_not_answer_wait_for_it_then_run_a_job(
    bare_cluster: Cluster, scenes_dir, tmp_path
):
    """A scheduler and a worker started while their database refuses connections (Postgres restarting, a
    failover) wait for it (OMNIDATA_DB_WAIT_S) instead of exiting: they used to exit at once with `cannot
    reach the database` (as a worker whose connection the chaos soak cut while it started would). Then they
    run a
    job."""
    cluster = bare_cluster
    port = free_port()  # nothing listens there until the proxy to the real database starts
    db_url = make_url(cluster.pg_url).set(port=port).render_as_string(hide_password=False)
    procs = [cluster.start_scheduler(OMNIDATA_DATABASE_URL=db_url),
             cluster.start_worker("w0", OMNIDATA_DATABASE_URL=db_url)]
    wait(lambda: all("waiting up to 60 s for the database (" in p.tail() for p in procs), 60,
         "both to say they wait for the database", cluster)
    time.sleep(2.0)
    assert all(p.alive() for p in procs), cluster.logs()
    proxy = HoldingProxy(f"tcp://127.0.0.1:{make_url(cluster.pg_url).port or 5432}", port=port)
    try:
        job_id = submit_direct(cluster, scenes_dir / "ycb_banana", write_spec(tmp_path, FAULTS))
        wait_done(cluster, job_id, 180)
        assert_exactly_once(cluster, job_id)
        assert all(p.alive() for p in procs), cluster.logs()
    finally:
        proxy.close()
