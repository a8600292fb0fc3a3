"""The API over compacted views: views, tasks, one task, a view's outputs, throughput and the manifest answer
the same before and after compaction (services.scheduler.compaction), on Postgres and SQLite."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import func, select

from services.core.db.models import Task, ViewOutput
from services.core.storage import LocalStore
from services.scheduler.compaction import Compactor
from tests.fixtures.api import Api, fake_plan, make_api, run_tasks, task_ids

LINK_FIELDS = {"url", "preview_url", "expires_at"}  # signed with the time: differ between two calls
ROW_ONLY = {"worker_id", "queued_at", "started_at"}  # what a compacted task does not keep


def _views(api: Api, job_id: int, query: str) -> tuple[int, list[Any]]:
    r = api.client.get(f"/jobs/{job_id}/views?{query}", headers=api.a.headers)
    assert r.status_code == 200, r.text
    body = r.json()
    for item in body["items"]:
        for link in (item["outputs"] or {}).values():
            for k in LINK_FIELDS:
                link.pop(k)
    return body["total"], body["items"]


def _tasks(api: Api, job_id: int, query: str) -> tuple[int, list[Any]]:
    items, offset, total = [], 0, None
    while True:  # pages of 5: the last page of task rows runs into the compacted tasks
        body = api.client.get(
            f"/jobs/{job_id}/tasks?{query}&limit=5&offset={offset}", headers=api.a.headers
        ).json()
        total = body["total"]
        items += [{k: v for k, v in t.items() if k not in ROW_ONLY} for t in body["items"]]
        if len(body["items"]) < 5:
            return total, sorted(items, key=lambda t: t["id"])
        offset += 5


def _snapshot(api: Api, job_id: int, done_id: int) -> dict[str, Any]:
    h = api.a.headers
    outputs = api.client.get(f"/jobs/{job_id}/views/{_space(api, job_id)}/0/1/outputs", headers=h).json()
    for link in outputs["outputs"].values():
        for k in LINK_FIELDS:
            link.pop(k)
    one = api.client.get(f"/jobs/{job_id}/tasks/{done_id}", headers=h).json()
    tp = api.client.get(f"/jobs/{job_id}/throughput", headers=h).json()
    api.app.state.metrics_cache.clear()
    metrics = api.client.get("/metrics", headers=h).text
    durations = [line for line in metrics.splitlines() if line.startswith("omnidata_task_duration_seconds")]
    return {
        "views": _views(api, job_id, "urls=true"),
        "complete": _views(api, job_id, "complete=true"),
        "done_rgb": _views(api, job_id, "state=done&cue=rgb"),
        "nonfixated": _views(api, job_id, "cue=nonfixated"),
        "failed": _views(api, job_id, "state=failed"),
        "tasks": _tasks(api, job_id, "state=done"),
        "all_tasks": _tasks(api, job_id, "cue=rgb"),
        "space_tasks": _tasks(api, job_id, f"space_id={_space(api, job_id)}"),
        "one": {k: v for k, v in one.items() if k not in ROW_ONLY},
        "outputs": outputs,
        "throughput": sum(b["done"] for b in tp["buckets"]),
        "durations": durations,
        "manifest": api.client.get(f"/jobs/{job_id}/manifest.jsonl", headers=h).content,
    }


def _space(api: Api, job_id: int) -> int:
    return api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()["space_ids"][0]


def _check(api: Api, bunny: Path) -> None:
    h = api.a.headers
    sid = api.client.post("/spaces", files={"file": ("bunny.ply", bunny.read_bytes())}, headers=h).json()[
        "id"
    ]
    r = api.client.post(
        "/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb", "depth_zbuffer", "nonfixated"]}},
        headers=h,
    )
    job_id = int(r.json()["id"])
    with api.session() as s:
        fake_plan(s, job_id, points=3, views=2)
        p0 = [int(i) for i in s.scalars(select(Task.id).where(Task.job_id == job_id, Task.point_idx == 0))]
        run_tasks(s, api.store, job_id, p0)
        p1 = [int(i) for i in s.scalars(select(Task.id).where(Task.job_id == job_id, Task.point_idx == 1,
                                                             Task.view_idx == 1))]
        run_tasks(s, api.store, job_id, p1)
        run_tasks(s, api.store, job_id, task_ids(s, job_id, state="pending", cue="rgb")[:1], fail=True)
    before = _snapshot(api, job_id, p0[1])
    Compactor(api.sessions, after_s=0, pass_s=60).run_once()  # (jobs other tests left in the database too)
    with api.session() as s:  # point 0's two views and point 1's view 1
        assert s.scalar(select(func.count()).select_from(ViewOutput).where(ViewOutput.job_id == job_id)) == 3
        assert s.scalar(select(func.count()).select_from(Task).where(Task.id == p0[1])) == 0
    after = _snapshot(api, job_id, p0[1])
    assert before["views"][1][0]["state"] == "done" and before["complete"][0] == 3
    assert len(before["durations"]) == 4 * 15 and before["throughput"] == len(p0) + len(p1)
    assert before["tasks"][0] == len(p0) + len(p1) and before["outputs"]["outputs"]["nonfixated"]
    for key in before:
        assert after[key] == before[key], key


def test_the_api_answers_the_same_after_compaction_postgres(api: Api, bunny: Path) -> None:
    _check(api, bunny)


def test_the_api_answers_the_same_after_compaction_sqlite(sqlite_url: str, local_store: LocalStore,
                                                          bunny: Path) -> None:
    with make_api(sqlite_url, local_store) as api:
        _check(api, bunny)

