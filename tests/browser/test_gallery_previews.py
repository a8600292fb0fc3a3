"""The gallery shows readable previews of real renders: every cue tile varies (no black or white 16-bit
images, no text tiles for npy/exr/json), fetched from the API's preview route by headless Chromium."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from services.core.db.jobs import root_key
from services.core.db.models import Job
from services.core.domain.keys import output_key
from services.core.storage import LocalStore
from tests.conftest import GeneratedRun
from tests.fixtures.api import fake_plan, live_server, make_api, run_tasks, task_ids

pytestmark = pytest.mark.slow

CUES = ["rgb", "normal", "depth_zbuffer", "principal_curvature", "edge_texture", "keypoints2d",
        "segment_unsup2d", "fragments", "position", "point_info", "nonfixated", "vanishing_points"]

# the standard deviation of each gallery image's pixels, drawn on a canvas (same origin: readable)
PIXEL_STD = """() => [...document.querySelectorAll('#job-gallery img')].map((img) => {
  const c = document.createElement('canvas'); c.width = img.naturalWidth; c.height = img.naturalHeight;
  const g = c.getContext('2d'); g.drawImage(img, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data; let s = 0, s2 = 0, n = 0;
  for (let i = 0; i < d.length; i += 4)
    for (let k = 0; k < 3; k++) { s += d[i + k]; s2 += d[i + k] ** 2; n++; }
  return [img.alt, Math.sqrt(s2 / n - (s / n) ** 2)];
})"""


def test_gallery_previews_of_real_renders(
    pg_url: str, local_store: LocalStore, scenes_dir: Path, browser: Any, artifacts: Path,
    tiny_banana: GeneratedRun,
) -> None:
    rendered = tiny_banana.out
    bunny = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    with make_api(pg_url, local_store) as api, live_server(api.app) as base:
        r = api.client.post(
            "/spaces", files={"file": ("bunny.ply", bunny.read_bytes())}, headers=api.a.headers
        )
        r = api.client.post("/jobs", json={"space_ids": [r.json()["id"]], "spec": {"cues": CUES}},
                            headers=api.a.headers)
        job_id = int(r.json()["id"])
        with api.session() as s:
            fake_plan(s, job_id, points=2, views=2)
            run_tasks(s, api.store, job_id, task_ids(s, job_id))
            job = s.get(Job, job_id)
            assert job is not None
            # the finished tasks' objects become the real renders of the banana job (same points and views)
            for f in rendered.glob("*/tiny/ycb_banana/*"):
                cue, name = f.parts[-4], f.name
                if cue in CUES:
                    p, v = int(name.split("_")[1]), int(name.split("_")[3]) if "_view_" in name else 0
                    api.store.put_bytes(
                        root_key(job, output_key(cue, job.name, "bunny", p, v)), f.read_bytes()
                    )
        ctx = browser.new_context(viewport={"width": 1600, "height": 900})
        try:
            page = ctx.new_page()
            failed: list[str] = []
            page.on(
                "response",
                lambda resp: failed.append(f"{resp.status} {resp.url}") if resp.status >= 400 else None,
            )
            page.goto(f"{base}/ui/")
            page.evaluate(f"sessionStorage.setItem('omnidata.token', {api.a.token!r})")
            page.goto(f"{base}/ui/#/jobs/{job_id}")
            page.wait_for_selector("#job-gallery .view-row")
            page.wait_for_function(
                "() => [...document.querySelectorAll('#job-gallery img')].length > 0 && "
                "[...document.querySelectorAll('#job-gallery img')].every(i => i.complete && "
                "i.naturalWidth > 0)",
                timeout=30_000,
            )
            stds = page.evaluate(PIXEL_STD)
            page.screenshot(path=str(artifacts / "dashboard-gallery-previews.png"), full_page=True)
        finally:
            ctx.close()
    assert not failed, failed
    # every cue an image, none a text tile
    assert len(stds) == 4 * len(CUES) and {alt for alt, _ in stds} == set(CUES)
    flat = [(alt, round(sd, 1)) for alt, sd in stds if sd < 5]
    assert not flat, f"near-constant previews: {flat}"
