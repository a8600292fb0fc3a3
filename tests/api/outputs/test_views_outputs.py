"""Views, tasks, plan, throughput, output links (local signed links and S3 pre-signed URLs), manifest,
job.json."""

from __future__ import annotations

import json
import time
from collections import Counter
from datetime import datetime
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import httpx
import pytest
from sqlalchemy import select

from services.core.db.models import Task, TaskState
from services.core.storage import open_store
from tests.fixtures.api import Api, fake_plan, make_api, run_tasks, task_ids


def _job(api: Api, bunny: Path, cues: list[str], points: int = 3, views: int = 2) -> int:
    r = api.client.post("/spaces", files={"file": ("bunny.ply", bunny.read_bytes())}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    r = api.client.post(
        "/jobs", json={"space_ids": [r.json()["id"]], "spec": {"cues": cues}}, headers=api.a.headers
    )
    assert r.status_code == 201, r.text
    job_id = int(r.json()["id"])
    with api.session() as s:
        fake_plan(s, job_id, points=points, views=views)
    return job_id


def test_views_tasks_filters_and_pagination(api: Api, bunny: Path) -> None:
    h = api.a.headers
    job_id = _job(api, bunny, ["rgb", "depth_zbuffer", "nonfixated"])
    with api.session() as s:
        ids = task_ids(s, job_id)
        # finish point 0 entirely; fail one rgb task of point 1
        from services.core.db.models import Task

        p0 = [t.id for t in s.query(Task).filter(Task.job_id == job_id, Task.point_idx == 0)]
        run_tasks(s, api.store, job_id, p0)
        rgb_p1 = [
            t.id
            for t in s.query(Task)
            .filter(Task.job_id == job_id, Task.point_idx == 1, Task.cue == "rgb")
            .order_by(Task.view_idx)
        ]  # view 0 first: a row order without ORDER BY is the heap's
        run_tasks(s, api.store, job_id, rgb_p1[:1], fail=True)
    r = api.client.get(f"/jobs/{job_id}/views?limit=4", headers=h).json()
    assert r["total"] == 6 and len(r["items"]) == 4
    v0 = r["items"][0]
    assert (v0["point"], v0["view"]) == (0, 0) and v0["state"] == "done"
    assert set(v0["tasks"]) == {"passes", "rgb", "depth_zbuffer", "nonfixated"}
    assert v0["fov_deg"] == pytest.approx(77.35, abs=0.01) and len(v0["world_to_camera"]) == 16
    assert r["items"][1]["tasks"]["nonfixated"]["state"] == "done"  # per-point cue shown on view 1 as well
    assert r["items"][2]["state"] == "failed"
    assert r["items"][2]["tasks"]["rgb"]["error"].startswith("RuntimeError")
    page2 = api.client.get(f"/jobs/{job_id}/views?limit=4&offset=4", headers=h).json()
    assert [(v["point"], v["view"]) for v in page2["items"]] == [(2, 0), (2, 1)]
    done = api.client.get(f"/jobs/{job_id}/views?complete=true", headers=h).json()
    assert [(v["point"], v["view"]) for v in done["items"]] == [(0, 0), (0, 1)] and done["total"] == 2
    failed = api.client.get(f"/jobs/{job_id}/views?state=failed&cue=rgb", headers=h).json()
    assert failed["total"] == 1 and failed["items"][0]["point"] == 1
    assert api.client.get(f"/jobs/{job_id}/views?cue=nope", headers=h).status_code == 422

    tasks = api.client.get(f"/jobs/{job_id}/tasks?state=failed", headers=h).json()
    assert tasks["total"] == 1 and tasks["items"][0]["error"].startswith("RuntimeError: the test")
    assert tasks["items"][0]["attempts"] == 1 and tasks["items"][0]["worker_id"] == "test-worker:1"
    all_rgb = api.client.get(f"/jobs/{job_id}/tasks?cue=rgb&limit=2", headers=h).json()
    assert all_rgb["total"] == 6 and len(all_rgb["items"]) == 2
    assert api.client.get(f"/jobs/{job_id}/tasks", headers=h).json()["total"] == len(ids)
    one = api.client.get(f"/jobs/{job_id}/tasks/{ids[0]}", headers=h).json()
    assert one["id"] == ids[0] and one["state"] == "done" and one["output_key"].startswith(f"jobs/{job_id}/")
    assert api.client.get(f"/jobs/{job_id}/tasks/{ids[-1] + 10_000}", headers=h).status_code == 404


def test_plan_and_throughput(api: Api, bunny: Path) -> None:
    h = api.a.headers
    job_id = _job(api, bunny, ["rgb"], points=5, views=3)
    plan = api.client.get(f"/jobs/{job_id}/plan", headers=h).json()
    (sp,) = plan["spaces"]
    assert len(sp["cameras"]) == 4 and len(sp["points"]) == 5 and len(sp["views"]) == 15
    assert len(sp["bounds"]) == 2 and sp["truncated"] is False and len(sp["cameras"][0]) == 4
    assert (
        api.client.get(f"/jobs/{job_id}/plan?max_items=2", headers=h).json()["spaces"][0]["truncated"] is True
    )
    assert api.client.get(f"/jobs/{job_id}/throughput", headers=h).json()["buckets"] == []
    with api.session() as s:
        run_tasks(s, api.store, job_id, task_ids(s, job_id)[:7])
    from services.api.views.service import _throughput_cache

    _throughput_cache._data.clear()
    tp = api.client.get(f"/jobs/{job_id}/throughput?buckets=20", headers=h).json()
    assert sum(b["done"] for b in tp["buckets"]) == 7 and tp["bucket_s"] >= 1.0
    # each task in the bucket its finish time falls in, counted from the first bucket's start
    with api.session() as s:
        finished = s.scalars(select(Task.finished_at).where(Task.job_id == job_id,
                                                            Task.state == TaskState.DONE)).all()
    start = datetime.fromisoformat(tp["buckets"][0]["t"])  # UTC, as the stored finish times (UTCDateTime)
    expected = Counter(int((f - start).total_seconds() // tp["bucket_s"]) for f in finished if f is not None)
    assert {i: b["done"] for i, b in enumerate(tp["buckets"]) if b["done"]} == dict(expected)


def test_outputs_local_signed_links(api: Api, bunny: Path) -> None:
    h = api.a.headers
    job_id = _job(api, bunny, ["rgb", "depth_zbuffer", "point_info"], points=1, views=1)
    with api.session() as s:
        run_tasks(s, api.store, job_id, task_ids(s, job_id))
    r = api.client.get(f"/jobs/{job_id}/views/{_space(api, job_id)}/0/0/outputs", headers=h)
    assert r.status_code == 200, r.text
    outs = r.json()["outputs"]
    assert list(outs) == ["rgb", "depth_zbuffer", "point_info"]  # catalog order, internal passes left out
    rgb = outs["rgb"]
    assert (
        rgb["key"] == "rgb/omnidata/bunny/point_0_view_0_domain_rgb.png"
        and rgb["content_type"] == "image/png"
    )
    got = api.client.get(rgb["url"])  # no token: the signature is the credential
    assert got.status_code == 200 and got.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert got.content == api.store.get_bytes(f"jobs/{job_id}/{rgb['key']}")
    q = parse_qs(urlparse(rgb["url"]).query)
    assert int(q["expires"][0]) - time.time() == pytest.approx(3600, abs=30)
    path = urlparse(rgb["url"]).path
    bad = api.client.get(f"{path}?job={job_id}&expires={q['expires'][0]}&signature={'0' * 64}")
    assert bad.status_code == 403 and "signature" in bad.json()["detail"]
    other_path = path.replace("rgb.png", "x.png")
    other = api.client.get(
        f"{other_path}?job={job_id}&expires={q['expires'][0]}&signature={q['signature'][0]}"
    )
    assert other.status_code == 403
    from services.api.outputs.service import blob_signature

    past = int(time.time()) - 5
    sig = blob_signature(api.app.state.settings, f"jobs/{job_id}/{rgb['key']}", past, job_id=job_id)
    expired = api.client.get(f"{path}?job={job_id}&expires={past}&signature={sig}")
    assert expired.status_code == 403 and "expired" in expired.json()["detail"]
    # the gallery gets the same links in one call
    views = api.client.get(f"/jobs/{job_id}/views?urls=true&complete=true", headers=h).json()
    assert list(views["items"][0]["outputs"]) == ["rgb", "depth_zbuffer", "point_info"]
    # no such view
    assert (
        api.client.get(f"/jobs/{job_id}/views/{_space(api, job_id)}/0/9/outputs", headers=h).status_code
        == 404
    )


def _space(api: Api, job_id: int) -> int:
    return int(api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()["space_ids"][0])


def test_manifest_and_job_json(api: Api, bunny: Path) -> None:
    h = api.a.headers
    job_id = _job(api, bunny, ["rgb", "normal"], points=2, views=2)
    with api.session() as s:
        run_tasks(s, api.store, job_id, task_ids(s, job_id))
    r = api.client.get(f"/jobs/{job_id}/manifest.jsonl", headers=h)
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/x-ndjson")
    lines = [json.loads(line) for line in r.text.splitlines()]
    assert [(x["point"], x["view"]) for x in lines] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert set(lines[0]["outputs"]) == {"rgb", "normal"} and lines[0]["outputs"]["rgb"]["size"] > 0
    doc = api.client.get(f"/jobs/{job_id}/job.json", headers=h).json()
    assert doc["spec"]["cues"] == ["rgb", "normal"] and "bunny" in doc["spaces"] and "conventions" in doc


def test_outputs_on_s3_are_presigned_and_expire(pg_url: str, s3_server, bunny: Path) -> None:  # type: ignore[no-untyped-def]
    settings = s3_server.settings(prefix="api-test")
    store = open_store(settings.storage_url, settings)
    with make_api(pg_url, store, **{k: getattr(settings, k) for k in (
        "storage_url", "s3_endpoint_url", "s3_region", "aws_access_key_id", "aws_secret_access_key")},
        presign_expiry_s=120,
    ) as api:
        job_id = _job(api, bunny, ["rgb"], points=1, views=1)
        with api.session() as s:
            run_tasks(s, store, job_id, task_ids(s, job_id))
        out = api.client.get(f"/jobs/{job_id}/views/{_space(api, job_id)}/0/0/outputs", headers=api.a.headers)
        link = out.json()["outputs"]["rgb"]
        assert link["url"].startswith(s3_server.endpoint_url)
        assert parse_qs(urlparse(link["url"]).query).get("Expires") or "X-Amz-Expires=120" in link["url"]
        got = httpx.get(link["url"])
        assert got.status_code == 200 and got.content[:4] == b"\x89PNG"
        # staged registration through an s3:// URI of the same store
        store.put_file(f"uploads/{api.a.name}/b.ply", bunny)
        r = api.client.post(
            "/spaces/register",
            json={"uri": f"{settings.storage_url}/uploads/{api.a.name}/b.ply", "name": "viauri"},
            headers=api.a.headers,
        )
        assert r.status_code == 201, r.text
