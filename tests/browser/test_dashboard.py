"""The dashboard end to end in headless Chromium against a real uvicorn server on Postgres.

Logs in, uploads a space, submits a job with the form, then completes tasks in the database the way
workers do and watches the job's progress bar advance to 100 % through server-sent events (no reload),
opens the job page (plan plot, throughput chart, gallery of finished views) and the workers page.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from services.core.db.models import Job, Worker, utcnow
from services.core.storage import LocalStore
from tests.fixtures.api import fake_plan, live_server, make_api, run_tasks, task_ids

pytestmark = pytest.mark.slow


def _fraction(page: Any, job_id: int) -> float:
    return float(page.get_attribute(f'tr[data-job-id="{job_id}"] .bar.overall', "data-fraction"))


def test_dashboard_live_progress_and_gallery(
    pg_url: str, local_store: LocalStore, scenes_dir: Path, browser: Any, artifacts: Path
) -> None:
    bunny = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    with make_api(pg_url, local_store) as api, live_server(api.app) as base:
        ctx = browser.new_context(viewport={"width": 1440, "height": 900})
        try:
            _run(api, base, ctx, bunny, artifacts)
        finally:
            ctx.close()  # closes the EventSource streams before the server stops


def _run(api: Any, base: str, ctx: Any, bunny: Path, artifacts: Path) -> None:
    page = ctx.new_page()
    console_errors: list[str] = []
    page.on("console", lambda m: console_errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: console_errors.append(str(e)))
    failed: list[str] = []
    page.on("response", lambda r: failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)

    # login: a wrong token is refused, the right one lands on the jobs page
    page.goto(f"{base}/ui/")
    page.wait_for_selector("#login-token")
    page.fill("#login-token", "wrong-token")
    page.click("#login-submit")
    page.wait_for_selector("#login-error:has-text('Login failed')")
    assert failed == [f"401 {base}/jobs?limit=1"] and len(console_errors) == 1  # the refused login only
    failed.clear()
    console_errors.clear()
    page.fill("#login-token", api.a.token)
    page.click("#login-submit")
    page.wait_for_selector("h1:has-text('Jobs')")
    page.screenshot(path=str(artifacts / "dashboard-01-jobs-empty.png"), full_page=True)

    # upload a space with the form
    page.set_input_files("#upload-file", str(bunny))
    page.fill("#upload-name", "bunny")
    page.click("#upload-submit")
    page.wait_for_selector("#upload p:has-text('registered')", timeout=30_000)
    page.wait_for_selector("#job-space option", state="attached")

    # submit a small job with the form
    page.fill("#job-points", "2")
    page.fill("#job-resolution", "64")
    page.fill("#job-seed", "3")
    page.click("#job-submit")
    page.wait_for_selector("tr[data-job-id]")
    job_id = int(page.get_attribute("tr[data-job-id]", "data-job-id"))
    with api.session() as s:
        job = s.get(Job, job_id)
        assert job is not None and job.owner == api.a.name
        assert job.spec["views"]["resolution"] == 64 and job.spec["seed"] == 3
        assert job.spec["points"]["count"] == 2 and job.spec["cues"] == ["rgb", "normal", "depth_zbuffer"]
    page.evaluate("window.__noReload = 1")
    page.screenshot(path=str(artifacts / "dashboard-02-job-submitted.png"), full_page=True)

    # plan it and complete its tasks in batches, as the scheduler and workers would
    with api.session() as s:
        fake_plan(s, job_id, points=2, views=2)
        ids = task_ids(s, job_id)
    page.wait_for_selector(f'tr[data-job-id="{job_id}"][data-state="running"]')
    seen = [_fraction(page, job_id)]
    batches = [ids[i : i + 4] for i in range(0, len(ids), 4)]
    for batch in batches:
        with api.session() as s:
            run_tasks(s, api.store, job_id, batch)
        deadline = time.monotonic() + 20
        while _fraction(page, job_id) <= seen[-1] and time.monotonic() < deadline:
            time.sleep(0.05)
        seen.append(_fraction(page, job_id))
    assert seen[0] == 0.0 and seen[-1] == 1.0, seen
    assert all(b > a for a, b in zip(seen, seen[1:], strict=False)), seen  # advanced at every batch
    assert any(0.0 < f < 1.0 for f in seen)
    with api.session() as s:  # the scheduler's completion step
        job = s.get(Job, job_id)
        assert job is not None
        job.state, job.finished_at = "done", utcnow()
        s.commit()
    page.wait_for_selector(f'tr[data-job-id="{job_id}"][data-state="done"]')
    assert page.evaluate("window.__noReload") == 1  # all of that arrived live, without a reload
    assert "100.0%" in page.inner_text(f'tr[data-job-id="{job_id}"] .bar.overall')
    cue_bars = page.query_selector_all(f'tr[data-job-id="{job_id}"] .cues .bar')
    assert len(cue_bars) == 4  # passes + the three cues
    page.screenshot(path=str(artifacts / "dashboard-03-job-done.png"), full_page=True)

    # job page: plan plot, throughput chart, gallery with every cue side by side
    page.click(f'tr[data-job-id="{job_id}"] td a')
    page.wait_for_selector("#job-gallery .view-row")
    # each panel loads on its own: the plan may come last
    page.wait_for_selector("#job-plan svg circle.point")
    assert len(page.query_selector_all("#job-plan svg circle.point")) == 2
    assert len(page.query_selector_all("#job-plan svg polygon.camera")) == 4
    page.wait_for_selector("#job-throughput svg rect", state="attached")
    heights = page.eval_on_selector_all(
        "#job-throughput svg rect", "rs => rs.map(r => +r.getAttribute('height'))"
    )
    assert max(heights) > 0
    rows = page.query_selector_all("#job-gallery .view-row")
    assert len(rows) == 4
    page.wait_for_function(
        "() => [...document.querySelectorAll('#job-gallery img')].every(i => i.complete && "
        "i.naturalWidth > 0)"
    )
    imgs = rows[0].query_selector_all("img")
    # 16-bit depth shown too
    assert [i.get_attribute("alt") for i in imgs] == ["rgb", "normal", "depth_zbuffer"]
    # readable previews, not raw files
    assert all("/previews/" in (i.get_attribute("src") or "") for i in imgs)
    page.wait_for_selector("#job-failures:has-text('No failed tasks')")
    page.screenshot(path=str(artifacts / "dashboard-04-job-page.png"), full_page=True)

    # workers page
    with api.session() as s:
        s.add(Worker(id=f"browser-{api.a.name}:1", host="laptop", queues=["render"], last_heartbeat=utcnow(),
                     labels_per_s=12.5, tasks_done=30))
        s.commit()
    page.click("nav a[data-nav=workers]")
    page.wait_for_selector(f'tr[data-worker-id="browser-{api.a.name}:1"]')
    row = page.inner_text(f'tr[data-worker-id="browser-{api.a.name}:1"]')
    assert "laptop" in row and "12.5" not in row  # service-wide throughput: operators only
    page.screenshot(path=str(artifacts / "dashboard-05-workers.png"), full_page=True)

    # logging out forgets the token
    page.click("#logout")
    page.wait_for_selector("#login-token")
    assert page.evaluate("sessionStorage.getItem('omnidata.token')") is None
    assert not console_errors and not failed, (console_errors, failed)
    with api.session() as s:
        assert s.scalar(select(Job.state).where(Job.id == job_id)) == "done"
