"""Operability through the real API app (issue 11): /ready checks the schema revision and the object store,
storage failures are named (503), /metrics is scoped per tenant or needs an operator token, `?token=` never
reaches the access log, and silent workers' rows expire."""

from __future__ import annotations

import secrets
import shutil
import time
from contextlib import AbstractContextManager
from datetime import timedelta
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from services.core.db.engine import downgrade, migrate
from services.core.db.models import Space, Task, Worker, utcnow
from services.core.db.worker_rows import expire_worker_rows
from services.core.settings import hash_token
from services.core.storage import LocalStore, open_store
from tests.conftest import S3Server
from tests.fixtures.api import Api, fake_plan, live_server, make_api, task_ids

OPERATOR_TOKEN = secrets.token_urlsafe(24)
OPERATOR = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}


# ---------------------------------------------------------------------------------------------- /ready


def test_ready_fails_on_an_unmigrated_then_an_outdated_database(
    empty_pg_url: str, local_store: LocalStore
) -> None:
    with make_api(empty_pg_url, local_store) as api:
        r = api.client.get("/ready")
        assert r.status_code == 503 and r.json()["failed"] == ["schema"], r.text
        assert r.json()["checks"]["database"]["ok"] is True
        detail = api.client.get("/ready", headers=api.a.headers).json()["detail"]
        assert "not migrated" in detail and "omnidata migrate" in detail

        migrate(empty_pg_url, "0001")
        detail = api.client.get("/ready", headers=api.a.headers).json()["detail"]
        assert "at revision 0001" in detail and "omnidata migrate" in detail

        migrate(empty_pg_url)
        r = api.client.get("/ready")
        assert r.status_code == 200 and r.json()["checks"]["schema"]["ok"] is True
        assert api.client.get("/jobs", headers=api.a.headers).status_code == 200
        downgrade(empty_pg_url, "base")  # leave nothing for drop_pg_database to trip on


def test_ready_fails_when_the_object_folder_is_gone(pg_url: str, tmp_path: Path) -> None:
    store = LocalStore(tmp_path / "objects")
    with make_api(pg_url, store) as api:
        assert api.client.get("/ready").status_code == 200
        assert not list(store.list())  # the probe cleans up after itself
        shutil.rmtree(store.root)
        assert api.client.get("/ready").status_code == 200  # the probe's outcome is kept a few seconds
        api.app.state.storage_probe = None
        r = api.client.get("/ready", headers=api.a.headers)
        assert r.status_code == 503 and r.json()["failed"] == ["storage"]
        assert f"object folder {store.root} does not exist" in r.json()["detail"]
        assert not store.root.exists()  # a probe does not paper over a vanished mount


def _s3_api(pg_url: str, s3_server: S3Server, bucket: str) -> AbstractContextManager[Api]:
    """The API on an S3 store in `bucket` of the moto endpoint (which may not exist)."""
    return make_api(pg_url, open_store(f"s3://{bucket}/data", s3_server.settings()))


def test_missing_bucket_fails_ready_and_uploads_with_a_named_503(
    pg_url: str, s3_server: S3Server, bunny: Path
) -> None:
    missing = f"missing-{secrets.token_hex(4)}"
    with _s3_api(pg_url, s3_server, missing) as api:
        r = api.client.get("/ready", headers=api.a.headers)
        assert r.status_code == 503 and r.json()["failed"] == ["storage"]
        assert f"the bucket s3://{missing} does not exist" in r.json()["checks"]["storage"]["error"]

        r = api.client.post("/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers)
        assert r.status_code == 503, r.text
        assert r.json()["detail"] == f"object storage unavailable: the bucket s3://{missing} does not exist"
        with api.session() as s:  # nothing partial: the space row went with the failed write
            assert s.scalar(select(func.count()).select_from(Space).where(Space.owner == api.a.name)) == 0

    with _s3_api(pg_url, s3_server, s3_server.bucket) as api:
        r = api.client.get("/ready")
        assert r.status_code == 200 and r.json()["checks"]["storage"]["ok"] is True
        assert api.client.post("/spaces", files={"file": ("b.ply", bunny.read_bytes())},
                               headers=api.a.headers).status_code == 201
        assert not api.store.exists("_ready/probe")


# ---------------------------------------------------------------------------------------------- /metrics


def _samples(text: str) -> dict[str, float]:
    return {k: float(v) for k, v in (ln.rsplit(" ", 1) for ln in text.splitlines() if ln and ln[0] != "#")}


def test_metrics_are_scoped_to_the_tenant_unless_operator(
    pg_url: str, local_store: LocalStore, bunny: Path
) -> None:
    with make_api(pg_url, local_store, operator_tokens=[hash_token(OPERATOR_TOKEN)]) as api:
        sid = api.client.post("/spaces", files={"file": ("b.ply", bunny.read_bytes())},
                              headers=api.a.headers).json()["id"]
        job_id = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}},
                                 headers=api.a.headers).json()["id"]
        with api.session() as s:
            fake_plan(s, job_id)
            n_tasks = len(task_ids(s, job_id))
            everyone = s.scalar(select(func.count()).select_from(Task))
            assert everyone is not None and n_tasks > 0

        assert api.client.get("/metrics").status_code == 401
        assert api.client.get("/metrics", headers={"Authorization": "Bearer nope"}).status_code == 401
        mine = _samples(api.client.get("/metrics", headers=api.a.headers).text)
        theirs = _samples(api.client.get("/metrics", headers=api.b.headers).text)
        operator = api.client.get("/metrics", headers=OPERATOR)
        assert operator.status_code == 200
        service = _samples(operator.text)

        assert sum(v for k, v in mine.items() if k.startswith("omnidata_tasks{")) == n_tasks
        assert mine['omnidata_jobs{state="running"}'] == 1
        assert sum(v for k, v in theirs.items() if k.startswith("omnidata_tasks{")) == 0
        assert sum(v for k, v in theirs.items() if k.startswith("omnidata_jobs{")) == 0
        # other tenants' work
        assert not any(k.startswith("omnidata_queue_depth") for k in {**mine, **theirs})
        # the operator sees every tenant's tasks (other tests' too: the database is shared) and the queues
        assert sum(v for k, v in service.items() if k.startswith("omnidata_tasks{")) >= n_tasks
        assert any(k.startswith("omnidata_queue_depth") for k in service)


# ---------------------------------------------------------------------------------------------- tokens in
# logs


def test_query_token_never_reaches_the_access_log(
    api: Api, bunny: Path, caplog: pytest.LogCaptureFixture
) -> None:
    sid = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
    ).json()["id"]
    job_id = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}},
                             headers=api.a.headers).json()["id"]
    secret = api.a.token
    with caplog.at_level("INFO", logger="uvicorn.access"), live_server(api.app, access_log=True) as base:
        # a bearer header AND ?token= (the case that used to be logged), on an SSE route and on others
        with httpx.stream("GET", f"{base}/jobs/{job_id}/events?token={secret}&x=1", headers=api.a.headers,
                          timeout=10) as r:
            assert r.status_code == 200
        assert httpx.get(f"{base}/jobs?token={secret}&limit=5", headers=api.a.headers).status_code == 200
        assert httpx.get(f"{base}/jobs?token={secret}&token=second").status_code == 401  # not auth off SSE
        assert httpx.get(f"{base}/ready?token={secret}").status_code == 200
        # ?token= alone still authenticates an EventSource client
        with httpx.stream("GET", f"{base}/jobs/{job_id}/events?token={secret}", timeout=10) as r:
            assert r.status_code == 200
        time.sleep(0.2)
    logged = [rec.getMessage() for rec in caplog.records if rec.name == "uvicorn.access"]
    assert len(logged) >= 5 and any("/jobs?limit=5" in m for m in logged), logged
    assert not any(secret in m or "second" in m or "token=" in m for m in logged), logged


# ---------------------------------------------------------------------------------------------- worker rows


def test_silent_worker_rows_expire_unless_they_hold_a_running_task(api: Api, bunny: Path) -> None:
    sid = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
    ).json()["id"]
    job_id = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}},
                             headers=api.a.headers).json()["id"]
    name = f"w-{api.a.name}"
    now = utcnow()
    with api.session() as s:
        fake_plan(s, job_id)
        tid = task_ids(s, job_id)[0]
        s.execute(
            Task.__table__.update().where(Task.id == tid).values(state="running", worker_id=f"{name}-held")
        )
        s.add_all(
            [
                Worker(
                    id=f"{name}-alive", host="h", queues=["render"], last_heartbeat=now - timedelta(seconds=5)
                ),
                Worker(
                    id=f"{name}-gone", host="h", queues=["render"], last_heartbeat=now - timedelta(hours=2)
                ),
                Worker(
                    id=f"{name}-held", host="h", queues=["render"], last_heartbeat=now - timedelta(hours=2)
                ),
            ]
        )
        s.commit()
        assert expire_worker_rows(s, older_than_s=3600) >= 1
    ids = {w["id"] for w in api.client.get("/workers?limit=1000", headers=api.a.headers).json()["items"]}
    assert {f"{name}-alive", f"{name}-held"} <= ids and f"{name}-gone" not in ids
