"""An S3 endpoint that answers 503 mid-job, on a real deployment (Postgres, Redis, moto over HTTP, the API,
the scheduler and two Celery workers): the job reads paused "storage unavailable ... answered 503" and /ready
fails, nothing fails or spends an attempt, and once the endpoint answers again work resumes within 30 s and
every output is stored exactly once. A module of its own: the folder-store test's deployment registered the
same scan in another store. The figures are printed (`pytest -s`).
"""

from __future__ import annotations

import time

import httpx
import pytest

from tests.e2e.test_distributed import assert_exactly_once, wait, wait_done
from tests.e2e.test_store_full import ENV, RESUME_BOUND_S, assert_held_not_failed, done_tasks, start_job
from tests.fixtures.holding_proxy import HoldingProxy

pytestmark = [pytest.mark.slow, pytest.mark.alone]



def test_an_s3_endpoint_answering_503_pauses_the_job_and_it_resumes(bare_cluster, s3_server, scenes_dir,
                                                                    tmp_path):
    """The scheduler and the workers reach the endpoint through a proxy that answers the
    writes under the deployment's prefix with 503 for a while (the API reaches it directly: its own probe
    passes, and /ready fails because a job waits for the store)."""
    cluster = bare_cluster
    proxy = HoldingProxy(s3_server.endpoint_url)
    try:
        api, auth, job_id = start_job(cluster, scenes_dir, tmp_path, OMNIDATA_S3_ENDPOINT_URL=proxy.url,
                                      **ENV)

        proxy.fail(f"PUT /{s3_server.bucket}/{cluster.prefix}/".encode())
        failing = time.monotonic()

        def job_read() -> dict:
            return httpx.get(f"{api}/jobs/{job_id}", headers=auth, timeout=10).json()

        wait(lambda: job_read()["state"] == "paused", 90, "the job to say it waits for the store", cluster)
        visible_s = time.monotonic() - failing
        read = job_read()
        assert read["paused_by"] == "storage" and "storage unavailable" in read["error"], read
        assert "answered 503 (ServiceUnavailable)" in read["error"], read
        wait(lambda: httpx.get(f"{api}/ready", timeout=10).status_code == 503, 30, "/ready to fail", cluster)
        ready = httpx.get(f"{api}/ready", headers=auth, timeout=10).json()
        assert ready["failed"] == ["storage"] and "job(s) wait for the store" in ready["detail"], ready
        assert_held_not_failed(cluster, job_id)

        stored_before = done_tasks(cluster, job_id)  # the writes in flight when it began included
        proxy.fail()
        recovered = time.monotonic()
        wait(lambda: done_tasks(cluster, job_id) > stored_before or job_read()["state"] == "done",
             RESUME_BOUND_S + 30, "work to resume", cluster)
        resumed_s = time.monotonic() - recovered
        wait_done(cluster, job_id, 300)
        done_s = time.monotonic() - recovered
        assert_exactly_once(cluster, job_id)
        print(f"\nS3 503 -> job paused (API) in {visible_s:.1f} s; endpoint back -> first task stored in "
              f"{resumed_s:.1f} s, job done in {done_s:.1f} s")
        assert resumed_s <= RESUME_BOUND_S, f"work resumed {resumed_s:.1f} s after the endpoint recovered"
    finally:
        proxy.close()
