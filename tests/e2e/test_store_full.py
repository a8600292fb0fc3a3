"""A store that fills up mid-job, on a real deployment (Postgres, Redis, the API, the scheduler and two Celery
workers as users start them) whose object store is a local folder on a small tmpfs: the ballast that fills it
is real, and so is every ENOSPC the workers meet.

The promise: within seconds the job reads paused "storage full" (API and database) and /ready says "storage
full"; no task fails and no attempt is spent meanwhile; once the ballast goes, work resumes within 30 s and
the job completes with every output present exactly once. The figures are printed (`pytest -s`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from services.core.db.counters import job_progress
from services.core.db.models import Job, Task, WorkerBlock
from services.core.storage import LocalStore
from tests.e2e.conftest import Cluster
from tests.e2e.test_distributed import assert_exactly_once, submit_direct, wait, wait_done, write_spec
from tests.fixtures.small_disk import fill, small_tmpfs

pytestmark = [pytest.mark.slow, pytest.mark.alone]

RESUME_BOUND_S = 30.0  # from the space's return to the first task stored again
ENV = {"OMNIDATA_HEARTBEAT_TIMEOUT_S": "6", "OMNIDATA_DISPATCH_WINDOW": "6"}
SPEC = """
cameras: {mode: object, object_count: 12}
points: {count: 24, min_views: 3, max_views: 3}
views: {resolution: 128}
cues: [rgb, normal, depth_zbuffer, point_info]
seed: 5
"""


@pytest.fixture()
def folder_cluster(bare_cluster: Cluster, tmp_path: Path) -> Iterator[Cluster]:
    """The deployment with its objects in a 48 MiB tmpfs instead of S3 (processes stopped before it goes)."""
    with small_tmpfs(tmp_path / "store", 48) as disk:
        bare_cluster.env["OMNIDATA_STORAGE_URL"] = str(disk)
        bare_cluster.store = LocalStore(disk)
        try:
            yield bare_cluster
        finally:
            bare_cluster.stop_all()


def done_tasks(cluster: Cluster, job_id: int) -> int:
    with cluster.sm() as s:
        return sum(by_state.get("done", 0) for by_state in job_progress(s, job_id).values())


def start_job(cluster: Cluster, scenes_dir: Path, tmp_path: Path,
              **env: str) -> tuple[str, dict[str, str], int]:
    """The API, a scheduler and two workers (the last two with `env`) running SPEC on the banana, once its
    first outputs are stored: (API url, auth headers, job id)."""
    api = cluster.start_api()
    cluster.start_scheduler(**env)
    job_id = submit_direct(cluster, scenes_dir / "ycb_banana", write_spec(tmp_path, SPEC))
    cluster.start_worker("worker-a", **env)
    cluster.start_worker("worker-b", **env)
    wait(lambda: done_tasks(cluster, job_id) >= 1, 180, "the job to store its first outputs", cluster)
    return api, {"Authorization": f"Bearer {cluster.token}"}, job_id


def assert_held_not_failed(cluster: Cluster, job_id: int) -> None:
    """While the store refuses writes: no task failed, no attempt spent beyond the first, no worker kept
    off."""
    with cluster.sm() as s:
        assert s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job_id,
                                                                      Task.state == "failed")) == 0
        assert s.scalar(select(func.max(Task.attempts)).where(Task.job_id == job_id)) <= 1
        assert s.scalars(select(WorkerBlock).where(WorkerBlock.job_id == job_id)).all() == []


def test_a_full_store_pauses_the_job_visibly_and_it_resumes_when_space_returns(folder_cluster, scenes_dir,
                                                                               tmp_path):
    cluster = folder_cluster
    api, auth, job_id = start_job(cluster, scenes_dir, tmp_path, **ENV)

    ballast = fill(Path(cluster.env["OMNIDATA_STORAGE_URL"]))
    filled = time.monotonic()

    def job_read() -> dict:
        return httpx.get(f"{api}/jobs/{job_id}", headers=auth, timeout=10).json()

    wait(lambda: job_read()["state"] == "paused", 60, "the job to say it waits for the store", cluster)
    visible_s = time.monotonic() - filled
    read = job_read()
    assert read["paused_by"] == "storage" and read["error"].startswith("storage full"), read
    wait(lambda: httpx.get(f"{api}/ready", timeout=10).status_code == 503, 30, "/ready to fail", cluster)
    ready_s = time.monotonic() - filled
    ready = httpx.get(f"{api}/ready", headers=auth, timeout=10).json()
    assert ready["failed"] == ["storage"] and "storage full" in ready["detail"], ready

    time.sleep(5)  # paused: nothing fails, nothing spends an attempt, no worker is kept off the job
    assert_held_not_failed(cluster, job_id)
    with cluster.sm() as s:
        assert s.get(Job, job_id).state == "paused"  # type: ignore[union-attr]
        # held by the workers (not by completion): tasks the store refused wait in pending, the reason kept
        assert s.scalar(select(func.count()).select_from(Task).where(
            Task.job_id == job_id, Task.state == "pending", Task.error.like("%storage full%"))) > 0

    stored_before = done_tasks(cluster, job_id)  # what went through before the fill, in flight then included
    ballast.unlink()
    freed = time.monotonic()
    wait(lambda: done_tasks(cluster, job_id) > stored_before or job_read()["state"] == "done",
         RESUME_BOUND_S + 30, "work to resume", cluster)
    resumed_s = time.monotonic() - freed
    wait_done(cluster, job_id, 300)
    done_s = time.monotonic() - freed
    assert_exactly_once(cluster, job_id)
    assert httpx.get(f"{api}/ready", timeout=10).status_code in (200, 503)  # the probe's cache may lag 5 s
    with cluster.sm() as s:
        total = s.get(Job, job_id).total_tasks  # type: ignore[union-attr]
    print(f"\nstore full -> job paused (API) in {visible_s:.1f} s, /ready 503 in {ready_s:.1f} s; "
          f"space back -> first task stored in {resumed_s:.1f} s, job done in {done_s:.1f} s "
          f"({stored_before} of {total} tasks stored before)")
    assert resumed_s <= RESUME_BOUND_S, f"work resumed {resumed_s:.1f} s after the space returned"

