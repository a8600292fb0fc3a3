"""Health, readiness (real Redis and Postgres; a dead broker), Prometheus metrics, workers."""

from __future__ import annotations

import secrets
from datetime import timedelta
from pathlib import Path

import redis

from services.core.db.models import Worker, utcnow
from services.core.settings import hash_token
from services.core.storage import LocalStore
from tests.fixtures.api import Api, fake_plan, free_port, make_api, run_tasks, task_ids

OPERATOR_TOKEN = secrets.token_urlsafe(24)
OPERATOR = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}  # service-wide /metrics (Prometheus)


def test_health_needs_no_token(api: Api) -> None:
    r = api.client.get("/health")
    assert r.status_code == 200 and r.json()["status"] == "ok"


def test_ready_checks_database_broker_storage(api: Api, redis_url: str) -> None:
    r = api.client.get("/ready")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["status"] == "ready" and body["failed"] == []
    assert set(body["checks"]) == {"database", "schema", "broker", "storage"}
    assert all(c["ok"] for c in body["checks"].values())


def test_ready_names_the_failed_dependency(pg_url: str, local_store: LocalStore) -> None:
    with make_api(pg_url, local_store, broker_url=f"redis://127.0.0.1:{free_port()}/0") as api:
        r = api.client.get("/ready")
        assert r.status_code == 503
        body = r.json()
        assert body["failed"] == ["broker"] and body["detail"] == "not ready: broker"
        assert "error" not in body["checks"]["broker"]  # no details without a token
        r = api.client.get("/ready", headers=api.a.headers)
        assert r.status_code == 503 and "Connection" in r.json()["checks"]["broker"]["error"]
        assert r.json()["detail"].startswith("not ready: broker (")


def test_metrics(pg_url: str, local_store: LocalStore, bunny: Path, redis_url: str) -> None:
    # queue names of our own: other tests may use the same Redis database at the same time
    queue = f"render-{secrets.token_hex(4)}"
    with make_api(pg_url, local_store, queue_render=queue, broker_url=redis_url,
                  operator_tokens=[hash_token(OPERATOR_TOKEN)]) as api:
        _check_metrics(api, bunny, redis_url, queue)


def _check_metrics(api: Api, bunny: Path, redis_url: str, queue: str) -> None:
    assert api.client.get("/metrics").status_code == 401
    sid = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
    ).json()["id"]
    job_id = api.client.post(
        "/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}}, headers=api.a.headers
    ).json()["id"]
    client = redis.Redis.from_url(redis_url)
    client.rpush(queue, b"m1", b"m2", b"m3")
    before = _metric_values(api)
    with api.session() as s:
        fake_plan(s, job_id)
        run_tasks(s, api.store, job_id, task_ids(s, job_id)[:3])
        s.add(Worker(id="w-metrics:1", host="h", queues=["render"], last_heartbeat=utcnow()))
        s.commit()
    api.app.state.metrics_cache.clear()
    r = api.client.get("/metrics", headers=OPERATOR)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    text = r.text
    assert "# TYPE omnidata_task_duration_seconds histogram" in text
    after = _metric_values(api, text)
    assert after['omnidata_tasks{state="done"}'] - before['omnidata_tasks{state="done"}'] == 3
    assert after["omnidata_tasks_dispatched_total"] - before["omnidata_tasks_dispatched_total"] == 3
    assert after[f'omnidata_queue_depth{{queue="{queue}"}}'] == 3
    assert after['omnidata_workers{status="alive"}'] >= 1
    inf = [k for k in after if k.startswith("omnidata_task_duration_seconds_bucket") and 'le="+Inf"' in k]
    assert sum(after[k] for k in inf) >= 3
    client.delete(queue)
    client.close()


def _metric_values(api: Api, text: str | None = None) -> dict[str, float]:
    if text is None:
        api.app.state.metrics_cache.clear()
        text = api.client.get("/metrics", headers=OPERATOR).text
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def test_workers_list_hides_other_tenants_tasks(api: Api, bunny: Path) -> None:
    sid = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
    ).json()["id"]
    job_id = api.client.post(
        "/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}}, headers=api.a.headers
    ).json()["id"]
    wid = f"w-{api.a.name}"
    with api.session() as s:
        fake_plan(s, job_id)
        tid = task_ids(s, job_id)[0]
        now = utcnow()
        s.add(
            Worker(
                id=wid + ":1", host="hostA", queues=["render", "derive"],
                last_heartbeat=now - timedelta(seconds=3), current_task_id=tid, tasks_done=12,
                labels_per_s=3.5, labels={"rgb": 12},
            )
        )
        s.add(
            Worker(id=wid + ":2", host="hostB", queues=["derive"], last_heartbeat=now - timedelta(minutes=5))
        )
        s.commit()
    items = {w["id"]: w for w in api.client.get("/workers?limit=1000", headers=api.a.headers).json()["items"]}
    w1, w2 = items[wid + ":1"], items[wid + ":2"]
    assert w1["alive"] is True and 2.5 < w1["heartbeat_age_s"] < 60
    assert w1["current_task"]["id"] == tid and w1["current_task"]["job_id"] == job_id and w1["busy"] is True
    assert w2["alive"] is False and w2["current_task"] is None and w2["busy"] is False
    other = {w["id"]: w for w in api.client.get("/workers?limit=1000", headers=api.b.headers).json()["items"]}
    assert other[wid + ":1"]["busy"] is True and other[wid + ":1"]["current_task"] is None
    # counts sum every tenant's work: neither tenant sees them (b would learn how much a renders, and what)
    for shown in (w1, other[wid + ":1"]):
        assert shown["labels"] == {} and shown["tasks_done"] is None and shown["labels_per_s"] is None
    assert "rgb" not in api.client.get("/workers?limit=1000", headers=api.b.headers).text
    alive = api.client.get("/workers?alive=true&limit=1000", headers=api.a.headers).json()["items"]
    assert wid + ":1" in {w["id"] for w in alive} and wid + ":2" not in {w["id"] for w in alive}


def test_worker_liveness_follows_the_configured_heartbeat_timeout(
    pg_url: str, local_store: LocalStore
) -> None:
    # The reaper declares a worker dead at OMNIDATA_HEARTBEAT_TIMEOUT_S: /workers and /metrics must agree with
    # it.
    with make_api(
        pg_url, local_store, heartbeat_timeout_s=10, operator_tokens=[hash_token(OPERATOR_TOKEN)]
    ) as api:
        wid = f"w-timeout-{secrets.token_hex(4)}"
        with api.session() as s:
            s.add(
                Worker(id=wid, host="h", queues=["render"], last_heartbeat=utcnow() - timedelta(seconds=20))
            )
            s.commit()
        items = {
            w["id"]: w for w in api.client.get("/workers?limit=1000", headers=api.a.headers).json()["items"]
        }
        assert items[wid]["alive"] is False
        stale = api.client.get("/workers?alive=false&limit=1000", headers=api.a.headers).json()["items"]
        assert wid in {w["id"] for w in stale}
        assert "alive: within 10 s" in api.client.get("/metrics", headers=OPERATOR).text


def test_workers_service_wide_figures_are_for_operators(
    pg_url: str, local_store: LocalStore, bunny: Path
) -> None:
    with make_api(pg_url, local_store, operator_tokens=[hash_token(OPERATOR_TOKEN)]) as api:
        sid = api.client.post(
            "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
        ).json()["id"]
        job_id = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}},
                                 headers=api.a.headers).json()["id"]
        wid = f"w-op-{secrets.token_hex(4)}"
        with api.session() as s:
            fake_plan(s, job_id)
            tid = task_ids(s, job_id)[0]
            s.add(Worker(id=wid, host="h", queues=["render"], last_heartbeat=utcnow(), current_task_id=tid,
                         tasks_done=12, labels_per_s=3.5, labels={"rgb": 12}))
            s.commit()
        seen = {w["id"]: w for w in api.client.get("/workers?limit=1000", headers=OPERATOR).json()["items"]}[
            wid
        ]
        assert seen["tasks_done"] == 12 and seen["labels_per_s"] == 3.5 and seen["labels"] == {"rgb": 12}
        assert seen["current_task"]["id"] == tid  # an operator sees every tenant's current task
        tenant_b = {
            w["id"]: w for w in api.client.get("/workers?limit=1000", headers=api.b.headers).json()["items"]
        }
        assert tenant_b[wid]["tasks_done"] is None and tenant_b[wid]["current_task"] is None
        assert api.client.get("/workers").status_code == 401
        assert api.client.get("/workers", headers={"Authorization": "Bearer nope"}).status_code == 401
