"""The API on the embedded database (SQLite): the same routes work without Postgres."""

from __future__ import annotations

from pathlib import Path

from services.core.storage import LocalStore
from tests.fixtures.api import fake_plan, make_api, run_tasks, task_ids


def test_api_on_sqlite(sqlite_url: str, local_store: LocalStore, scenes_dir: Path) -> None:
    bunny = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    with make_api(sqlite_url, local_store) as api:
        h = api.a.headers
        sid = api.client.post("/spaces", files={"file": ("bunny.ply", bunny.read_bytes())}, headers=h).json()[
            "id"
        ]
        job_id = api.client.post(
            "/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}}, headers=h
        ).json()["id"]
        with api.session() as s:
            fake_plan(s, job_id)
            run_tasks(s, api.store, job_id, task_ids(s, job_id)[:5])
            run_tasks(s, api.store, job_id, task_ids(s, job_id, state="pending")[:1], fail=True)
        job = api.client.get(f"/jobs/{job_id}", headers=h).json()
        assert job["progress"]["by_state"]["done"] == 5 and job["progress"]["by_state"]["failed"] == 1
        assert api.client.get("/jobs?state=running", headers=h).json()["total"] == 1
        views = api.client.get(f"/jobs/{job_id}/views?urls=true&complete=true", headers=h).json()
        assert views["total"] >= 1 and views["items"][0]["outputs"]["rgb"]["url"]
        assert api.client.get(f"/jobs/{job_id}/tasks?state=failed", headers=h).json()["total"] == 1
        tp = api.client.get(f"/jobs/{job_id}/throughput", headers=h).json()
        assert sum(b["done"] for b in tp["buckets"]) == 5
        assert len(api.client.get(f"/jobs/{job_id}/plan", headers=h).json()["spaces"][0]["points"]) == 2
        assert api.client.get(f"/jobs/{job_id}/manifest.jsonl", headers=h).status_code == 200
        assert "omnidata_tasks" in api.client.get("/metrics", headers=h).text
        assert api.client.get("/workers", headers=h).status_code == 200
        assert api.client.post(f"/jobs/{job_id}/cancel", headers=h).json()["state"] == "cancelled"
        assert api.client.delete(f"/jobs/{job_id}", headers=h).status_code == 204
