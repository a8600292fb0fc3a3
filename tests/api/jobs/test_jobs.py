"""Jobs: create (422 messages), list with filters and pagination, progress from counters, actions, delete."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from sqlalchemy import select

from services.api.jobs.progress import compute_progress
from services.api.jobs.rates import RateTracker
from services.core.db.models import Job, JobCounter, Task
from tests.fixtures.api import Api, fake_plan, run_tasks, task_ids


@pytest.fixture()
def space_id(api: Api, bunny: Path) -> int:
    r = api.client.post("/spaces", files={"file": ("bunny.ply", bunny.read_bytes())}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    return int(r.json()["id"])


def create(api: Api, space_ids: list[int], spec: dict | None = None, headers: dict | None = None):  # type: ignore[no-untyped-def]
    body = {"space_ids": space_ids, "spec": spec or {}}
    return api.client.post("/jobs", json=body, headers=headers or api.a.headers)


def test_create_job(api: Api, space_id: int) -> None:
    r = create(
        api, [space_id], {"name": "demo", "cues": ["rgb", "normal"], "seed": 7, "views": {"resolution": 64}}
    )
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["state"] == "pending" and job["name"] == "demo" and job["space_ids"] == [space_id]
    assert job["spec"]["seed"] == 7 and job["spec"]["views"]["resolution"] == 64
    assert job["spaces"][0]["cues"] == ["rgb", "normal"] and job["output_root"] == f"jobs/{job['id']}"
    assert job["progress"]["total"] == 0 and job["progress"]["fraction"] == 0.0
    assert r.headers["location"] == f"/jobs/{job['id']}"
    # default cues: everything an unlabelled space supports
    r = create(api, [space_id])
    assert r.status_code == 201 and "segment_semantic" not in r.json()["spaces"][0]["cues"]


@pytest.mark.parametrize(
    ("spec", "loc", "needle"),
    [
        ({"views": {"resolution": 100000}}, ["body", "spec", "views", "resolution"], "less than or equal"),
        (
            {"cues": ["rgb", "sparkles"]}, ["body", "spec", "cues"],
            "unknown cue(s): sparkles; known cues: rgb",
        ),
        ({"points": {"min_views": 5, "max_views": 2}}, ["body", "spec", "points"], "max_views (2) is below"),
        ({"bogus": 1}, ["body", "spec", "bogus"], "Extra inputs are not permitted"),
        (
            {"cameras": {"mode": "provided", "poses": [{"location": [0, 0, float("nan")]}] * 3}},
            ["body", "spec"], "finite",
        ),
        ({"name": "../x"}, ["body", "spec", "name"], "not a valid name"),
        (
            {"views": {"trajectory_look": "up"}}, ["body", "spec", "views", "trajectory_look"],
            "'point' or 'ahead'",
        ),
        (
            {"views": {"trajectory_min_frames": 40, "trajectory_max_frames": 20}}, ["body", "spec", "views"],
            "trajectory_min_frames (40) exceeds",
        ),
    ],
)
def test_invalid_spec_is_422_naming_the_field(
    api: Api, space_id: int, spec: dict, loc: list, needle: str
) -> None:
    r = api.client.post(
        "/jobs",
        content=__import__("json").dumps({"space_ids": [space_id], "spec": spec}),  # allows NaN in JSON
        headers={**api.a.headers, "Content-Type": "application/json"},
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert isinstance(body["detail"], str) and needle in body["detail"], body
    assert any(e["loc"][: len(loc)] == loc for e in body["errors"]), body["errors"]


def test_unsupported_cue_and_foreign_space(api: Api, space_id: int, bunny: Path) -> None:
    r = create(api, [space_id], {"cues": ["rgb", "segment_semantic"]})
    assert r.status_code == 422
    assert "segment_semantic" in r.json()["detail"] and "semantic labels" in r.json()["detail"]
    # another tenant's space: 404, and the job is not created
    r = create(api, [space_id], headers=api.b.headers)
    assert r.status_code == 404 and f"space {space_id} not found" == r.json()["detail"]
    r = create(api, [space_id, space_id])
    assert r.status_code == 422 and "repeat" in r.json()["detail"]
    assert create(api, []).status_code == 422
    assert api.client.get("/jobs", headers=api.a.headers).json()["total"] == 0


def test_list_filters_and_pagination(api: Api, space_id: int) -> None:
    ids = [create(api, [space_id], {"cues": ["rgb"]}).json()["id"] for _ in range(5)]
    with api.session() as s:
        fake_plan(s, ids[1])
        fake_plan(s, ids[2])
    r = api.client.get("/jobs?limit=2&offset=1", headers=api.a.headers)
    page = r.json()
    assert page["total"] == 5 and [j["id"] for j in page["items"]] == ids[::-1][1:3]
    r = api.client.get("/jobs?state=running", headers=api.a.headers)
    assert sorted(j["id"] for j in r.json()["items"]) == ids[1:3] and r.json()["total"] == 2
    r = api.client.get("/jobs?state=running&state=pending", headers=api.a.headers)
    assert r.json()["total"] == 5
    r = api.client.get("/jobs?state=exploded", headers=api.a.headers)
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["query", "state", 0]
    assert api.client.get("/jobs", headers=api.b.headers).json()["total"] == 0
    running = [j for j in api.client.get("/jobs?state=running", headers=api.a.headers).json()["items"]]
    assert all(j["progress"]["total"] == 2 * 2 * 2 for j in running)  # points x views x (passes, rgb)


def test_progress_counters_throughput_and_eta(api: Api, space_id: int) -> None:
    job_id = create(api, [space_id], {"cues": ["rgb", "normal", "nonfixated"]}).json()["id"]
    with api.session() as s:
        pending = fake_plan(s, job_id, points=3, views=2)
    assert pending == {"passes": 6, "rgb": 6, "normal": 6, "nonfixated": 3}
    r = api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()
    assert r["state"] == "running" and r["progress"]["total"] == 21
    assert r["progress"]["by_state"]["pending"] == 21 and r["progress"]["eta_s"] is None
    assert set(r["cues"]) == {"passes", "rgb", "normal", "nonfixated"}
    with api.session() as s:
        run_tasks(s, api.store, job_id, task_ids(s, job_id, cue="passes"))
        run_tasks(s, api.store, job_id, task_ids(s, job_id, cue="rgb")[:2], fail=True)
    # A fresh tracker: one reading, so the rate is the average since the start. With the first GET's reading
    # kept, a machine that took over 2 s (min_span_s) between them showed the windowed rate instead
    # (test_rate_tracker_uses_recent_window tests that one).
    api.app.state.rates = RateTracker()
    r = api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()
    p = r["progress"]
    assert p["by_state"]["done"] == 6 and p["by_state"]["failed"] == 2 and p["finished"] == 8
    assert p["fraction"] == pytest.approx(8 / 21, abs=1e-5)
    assert r["cues"]["passes"] == {"by_state": {**dict.fromkeys(p["by_state"], 0), "done": 6}, "total": 6,
                                   "done": 6, "fraction": 1.0}
    assert r["cues"]["rgb"]["by_state"]["failed"] == 2
    # the job started 10 s ago (fake planner): average throughput ~ 8 tasks / 10 s, ETA ~ 13 tasks / rate
    assert p["throughput_per_s"] == pytest.approx(0.8, rel=0.3)
    assert p["eta_s"] == pytest.approx(13 / p["throughput_per_s"], rel=0.05)
    assert p["labels_per_s"] == 0.0  # passes are internal, rgb tasks failed: no label yet
    # counters are the only source: a counter row changed behind the API's back shows up as is
    with api.session() as s:
        row = s.scalars(select(JobCounter).where(JobCounter.job_id == job_id, JobCounter.cue == "normal",
                                                 JobCounter.state == "pending").limit(1)).first()
        assert row is not None
        row.n += 1000
        s.commit()
    assert api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()["progress"]["total"] == 1021


def test_rate_tracker_uses_recent_window() -> None:
    rt = RateTracker(window_s=10.0, min_span_s=2.0)
    assert rt.observe(1, 0, 0, now=100.0) is None
    assert rt.observe(1, 10, 5, now=101.0) is None  # 1 s span: too short
    assert rt.observe(1, 40, 20, now=104.0) == pytest.approx((10.0, 5.0))
    rate = rt.observe(1, 140, 70, now=120.0)  # the first samples fell out of the 10 s window
    assert rate is not None and rate[0] == pytest.approx(100 / 16)
    assert rt.observe(1, 5, 0, now=121.0) is None  # counters went down (retry): window restarts


def test_rate_tracker_idle_time_makes_a_stalled_jobs_eta_unknown() -> None:
    rt = RateTracker(window_s=60.0, min_span_s=2.0)
    t0 = time.monotonic() - 40.0
    for k in range(10):  # a task finished every second, then none for 30 s
        rt.observe(7, k, k, now=t0 + k)
    assert rt.idle_s(7, now=t0 + 9) == pytest.approx(0.0)
    job = Job(id=7, state="running", owner="t", spec={})
    assert rt.idle_s(7, now=t0 + 39) == pytest.approx(30.0)
    progress, _ = compute_progress(job, {"rgb": {"done": 9, "running": 1}}, rt)
    # the window remembers the progress ...
    assert progress.throughput_per_s and progress.throughput_per_s > 0
    assert progress.eta_s is None  # ... but the ETA is unknown, not the 4 s the old rate would promise


def test_actions(api: Api, space_id: int) -> None:
    h = api.a.headers
    job_id = create(api, [space_id], {"cues": ["rgb"]}).json()["id"]
    r = api.client.post(f"/jobs/{job_id}/pause", headers=h)
    assert r.status_code == 409 and "only a running job can be paused" in r.json()["detail"]
    assert api.client.post(f"/jobs/{job_id}/retry", headers=h).status_code == 409
    with api.session() as s:
        fake_plan(s, job_id)
        run_tasks(s, api.store, job_id, task_ids(s, job_id)[:2], fail=True)
    assert api.client.post(f"/jobs/{job_id}/pause", headers=h).json()["state"] == "paused"
    assert api.client.post(f"/jobs/{job_id}/resume", headers=h).json()["state"] == "running"
    r = api.client.post(f"/jobs/{job_id}/retry", headers=h)
    assert r.status_code == 200 and r.json()["progress"]["by_state"]["failed"] == 0
    assert r.json()["progress"]["by_state"]["pending"] == 8
    with api.session() as s:
        assert all(t.attempts == 0 for t in s.scalars(select(Task).where(Task.job_id == job_id)))
    # another tenant: 404 on every action
    for action in ("cancel", "pause", "resume", "retry"):
        assert api.client.post(f"/jobs/{job_id}/{action}", headers=api.b.headers).status_code == 404
    r = api.client.post(f"/jobs/{job_id}/cancel", headers=h)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    assert r.json()["progress"]["by_state"]["cancelled"] == 8 and r.json()["progress"]["fraction"] == 1.0
    r = api.client.post(f"/jobs/{job_id}/cancel", headers=h)
    assert r.status_code == 409 and "cancelled" in r.json()["detail"]
    assert api.client.post(f"/jobs/{job_id}/resume", headers=h).status_code == 409


def test_delete_job_removes_outputs(api: Api, space_id: int) -> None:
    job_id = create(api, [space_id], {"cues": ["rgb"]}).json()["id"]
    with api.session() as s:
        fake_plan(s, job_id)
        run_tasks(s, api.store, job_id, task_ids(s, job_id))
    assert list(api.store.list(f"jobs/{job_id}/"))
    assert api.client.delete(f"/jobs/{job_id}", headers=api.b.headers).status_code == 404
    assert api.client.delete(f"/jobs/{job_id}", headers=api.a.headers).status_code == 204
    assert list(api.store.list(f"jobs/{job_id}/")) == []
    assert api.client.get(f"/jobs/{job_id}", headers=api.a.headers).status_code == 404
    with api.session() as s:
        assert s.get(Job, job_id) is None
        assert s.scalar(select(Task.id).where(Task.job_id == job_id)) is None
    # the space is free again
    assert api.client.delete(f"/spaces/{space_id}", headers=api.a.headers).status_code == 204


def test_isolation_and_not_found(api: Api, space_id: int) -> None:
    job_id = create(api, [space_id]).json()["id"]
    for path in ("", "/views", "/tasks", "/plan", "/throughput", "/job.json", "/manifest.jsonl", "/tasks/1",
                 "/views/1/0/0/outputs"):
        r = api.client.get(f"/jobs/{job_id}{path}", headers=api.b.headers)
        assert r.status_code == 404, (path, r.status_code)
        assert r.json()["detail"] == f"job {job_id} not found"
    assert api.client.get("/jobs/999999999", headers=api.a.headers).status_code == 404
    assert api.client.get("/jobs/0", headers=api.a.headers).status_code == 422
    assert api.client.get("/jobs/99999999999999999999999", headers=api.a.headers).status_code == 422
    assert api.client.get("/jobs/abc", headers=api.a.headers).status_code == 422


def test_job_spaces_show_the_planned_frame(api: Api, space_id: int) -> None:
    r = create(
        api, [space_id], {"source_to_world": [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]}
    )
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["spaces"][0]["frame"] is None  # not planned yet
    up = {"source_direction": [0.0, 1.0, 0.0], "method": "source_to_world", "confidence": "high"}
    with api.session() as s:
        row = s.get(Job, job["id"])
        row.plan_summary = {"spaces": {job["spaces"][0]["name"]: {"views": 3, "up": up, "warnings": []}}}
        s.commit()
    got = api.client.get(f"/jobs/{job['id']}", headers=api.a.headers).json()
    assert got["spaces"][0]["frame"] == {"up": up}
    bad = create(
        api, [space_id], {"source_to_world": [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
    )
    assert bad.status_code == 422 and "source_to_world" in bad.text and "uniform scale" in bad.text
