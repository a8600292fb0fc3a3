"""A scan uploaded with its capture (two parts of the upload form) through the dashboard (headless Chromium,
real uvicorn on Postgres): the photos are stored with the scan in object storage, the scheduler plans capture
views for real, and the job page summarises the capture (frames, intrinsics, lens) with a histogram of the
views' alignment scores."""

from __future__ import annotations

import queue
import zipfile
from pathlib import Path

import pytest

from services.core.db.models import Job, Space
from services.core.settings import get_settings
from services.core.storage import LocalStore
from services.scheduler.loop import Scheduler
from services.scheduler.transport import QueueTransport
from tests.browser.conftest import DashboardPage
from tests.fixtures.api import live_server, make_api

pytestmark = pytest.mark.slow


def test_capture_upload_plan_and_space_summary(
    pg_url: str, local_store: LocalStore, banana_capture_folder, dashboard_page: DashboardPage,
    artifacts: Path, tmp_path: Path,
) -> None:
    folder = banana_capture_folder[0]
    # two parts, as the form sends them: the scan (a zip of obj + mtl + texture) and the capture's zip
    upload, capture_zip = tmp_path / "banana_capture.zip", tmp_path / "photos.zip"
    with zipfile.ZipFile(upload, "w") as scan_zf, zipfile.ZipFile(capture_zip, "w") as cap_zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf = scan_zf if p.parent == folder and p.suffix in (".obj", ".mtl", ".png") else cap_zf
                zf.write(p, p.relative_to(folder).as_posix())
    with make_api(pg_url, local_store) as api, live_server(api.app) as base:
        with dashboard_page(base, api.a.token) as (page, errors):
            page.wait_for_selector("h1:has-text('Jobs')")
            page.set_input_files("#upload-file", str(upload))
            page.set_input_files("#upload-capture", str(capture_zip))
            page.fill("#upload-name", "banana_capture")
            page.click("#upload-submit")
            page.wait_for_selector("#upload p:has-text('Capture: colmap, 3 frames')", timeout=60_000)
            with api.session() as s:
                space = s.query(Space).filter_by(owner=api.a.name, name="banana_capture").one()
                assert (
                    space.validation["capture"]["format"] == "colmap"
                    and space.validation["capture"]["frames"] == 3
                )
                # photos stored with the scan
                with zipfile.ZipFile(local_store.root / space.source_key) as zf:
                    assert {"capture/images/photo_0.jpg", "capture/sparse/0/cameras.txt"} <= set(
                        zf.namelist()
                    )
                space_id = space.id
            res = api.client.post("/jobs", headers=api.a.headers, json={
                "space_ids": [space_id], "spec": {"cameras": {"mode": "capture"}, "views": {"resolution": 32},
                                                  "cues": ["rgb", "mask_photo"]}})
            assert res.status_code in (200, 201), res.text
            job_id = res.json()["id"]
            scheduler = Scheduler(api.sessions, local_store, QueueTransport(queue.Queue()), get_settings(),
                                  cache_dir=tmp_path / "cache")
            # other tests' jobs may still be pending in this session's database: plan until ours is planned
            assert any(job_id in scheduler.plan_pending(limit=5) for _ in range(50)), (
                "the capture job was not planned"
            )
            with api.session() as s:
                job = s.get(Job, job_id)
                planned = job.plan_summary["spaces"]["banana_capture"]
                assert planned["capture_plan"]["alignment"]["scored"] == 3
            page.goto(f"{base}/ui/#/jobs/{job_id}")
            page.wait_for_selector(".capture[data-space=banana_capture]")
            text = page.inner_text(".capture[data-space=banana_capture]")
            assert "colmap capture, 3 frames" in text and "200x150" in text and "opencv" in text
            bars = page.eval_on_selector_all(
                ".capture svg.alignment rect", "rs => rs.map(r => +r.getAttribute('height'))"
            )
            assert len(bars) == 10 and sum(h > 0 for h in bars) >= 1
            page.screenshot(path=str(artifacts / "dashboard-capture.png"), full_page=True)
            assert not errors
