"""The designer page on the ICL living room in headless Chromium: a 500-view spec planned and previewed, the
FOV range and the views per point changed in the form (histograms and previews follow, YAML follows), YAML
edited (the form follows), a bad spec's message shown, and specs A and B drawn overlaid.

The time from the last knob change to the updated histograms and previews is printed, and written to the file
named by OMNIDATA_DESIGNER_RESULTS when it is set (bench/results/designer_ui.json to record a run): never
asserted."""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import pytest

from services.core.storage import LocalStore
from tests.browser.conftest import DashboardPage
from tests.fixtures.api import live_server, make_api
from tests.fixtures.captures import transforms_zip

pytestmark = pytest.mark.slow

RESULTS_ENV = "OMNIDATA_DESIGNER_RESULTS"
SCREENSHOT_ENV = "OMNIDATA_DESIGNER_SCREENSHOT"  # where to save the page's picture (docs/img/designer.png)

HIST_A = "() => document.querySelector('.hist[data-name=fov_deg]')?.dataset.countsA || ''"
PREVIEWS_A = "() => [...document.querySelectorAll('#previews-a img')].map((i) => i.src)"
SPEC_SHOWN = """([sel, count, maxViews, fovMin, seed]) => {
  const spec = JSON.parse(document.querySelector(sel)?.dataset.spec || '{}');
  return spec.points?.count === count && spec.points?.max_views === maxViews
    && (spec.views?.fov_min_deg ?? null) === fovMin && (spec.seed ?? 0) === seed;
}"""


def _views(page: Any, slot: str) -> int:
    text = page.text_content(f"#design-slot-{slot} .summary") or ""
    return int(text.split(" views")[0])


def _steer(page: Any, slot: str, knobs: list[tuple[str, str]], shown: tuple[int, int, float | None],
           seed: int = 0) -> float:
    """Type `knobs` (and a seed: a plan never made before) into the form; seconds from the last one to the
    histograms and previews of that spec."""
    for knob, value in [("seed", str(seed)), *knobs]:
        page.fill(f"#knob-{knob}", value)
    t0 = time.perf_counter()
    page.wait_for_function(SPEC_SHOWN, arg=[f"#previews-{slot}", *shown, seed], timeout=120_000)
    return time.perf_counter() - t0


NARROW = [("views-fov_mean_deg", "50"), ("views-fov_min_deg", "40"), ("views-fov_max_deg", "60"),
          ("points-max_views", "4"), ("points-count", "125")]  # 125 points x 4 views: 500 views
DEFAULT_FOV = [("views-fov_max_deg", "125"), ("views-fov_min_deg", "30"), ("views-fov_mean_deg", "77.5"),
               ("points-count", "100"), ("points-max_views", "5")]  # back to 100 x 5
WIDE = [("views-fov_max_deg", "120"), ("views-fov_mean_deg", "100"), ("views-fov_min_deg", "80")]


def test_designer_steers_a_room(
    pg_url: str,
    local_store: LocalStore,
    scenes_dir: Path,
    tmp_path: Path,
    dashboard_page: DashboardPage,
    artifacts: Path,
) -> None:
    room = scenes_dir / "icl_livingroom" / "livingroom.obj"
    with make_api(pg_url, local_store, data_dir=str(tmp_path)) as api, live_server(api.app) as base:
        r = api.client.post(
            "/spaces", files={"file": ("livingroom.obj", room.read_bytes())}, headers=api.a.headers
        )
        assert r.status_code == 201, r.text
        with dashboard_page(base, api.a.token) as (page, errors):
            page.wait_for_selector("#nav:not([hidden])")
            opened = time.perf_counter()
            page.goto(f"{base}/ui/#/designer")
            # first plan and previews: the warm process starts (imports, Blender, the room's scene)
            page.wait_for_function(SPEC_SHOWN, arg=["#previews-a", 100, 5, None, 0], timeout=90_000)
            first_s = time.perf_counter() - opened
            assert _views(page, "a") == 500
            before_hist, before_previews = page.evaluate(HIST_A), page.evaluate(PREVIEWS_A)
            assert len(before_previews) == 4 * 4

            # the FOV range and the views per point, in the form: histograms, previews and YAML follow
            times = [_steer(page, "a", NARROW, (125, 4, 40.0))]
            after_hist, after_previews = page.evaluate(HIST_A), page.evaluate(PREVIEWS_A)
            assert after_hist != before_hist and after_previews != before_previews
            fovs = page.eval_on_selector_all(
                "#previews-a .design-preview", "els => els.map(e => e.dataset.fov)"
            )
            assert fovs and all(40 <= float(f) <= 60 for f in fovs), fovs
            views_after = _views(page, "a")
            assert "fov_min_deg: 40" in page.input_value("#design-yaml")
            for seed in (1, 2):  # more samples of the same change, back and forth, each a new plan
                times.append(_steer(page, "a", DEFAULT_FOV, (100, 5, None), seed))
                times.append(_steer(page, "a", NARROW, (125, 4, 40.0), seed))

            # A against B: B copies A, then its FOV goes wide; both series are drawn on every histogram
            page.click("#design-compare")
            _steer(page, "b", WIDE, (125, 4, 80.0), 2)
            page.wait_for_selector(".hist[data-name=fov_deg] .series-b rect")
            hist = page.eval_on_selector(
                ".hist[data-name=fov_deg]", "e => [e.dataset.countsA, e.dataset.countsB]"
            )
            assert hist[0] and hist[1] and hist[0] != hist[1]
            assert page.locator(".hist .series-a").count() == page.locator(".hist .series-b").count() == 7
            page.screenshot(
                path=os.environ.get(SCREENSHOT_ENV) or str(artifacts / "designer.png"), full_page=True
            )

            # B as a job, and as a YAML file
            with page.expect_download() as download:
                page.click("#design-download")
            assert "fov_min_deg: 80" in Path(download.value.path()).read_text()
            page.click("#design-create")
            page.wait_for_selector("#design-status a[href^='#/jobs/']")
            job = api.client.get(
                page.get_attribute("#design-status a", "href")[1:], headers=api.a.headers
            ).json()
            assert job["spec"]["views"]["fov_min_deg"] == 80.0 and job["spec"]["points"]["count"] == 125

            # YAML -> form, and a bad spec's message in the page
            page.fill("#design-yaml", "points:\n  count: 60\n  max_views: 5\n")
            page.wait_for_function("() => document.querySelector('#knob-points-count').value === '60'")
            page.fill("#design-yaml", "views:\n  resolution: 1\n")
            page.wait_for_function(
                "() => document.querySelector('#design-error').textContent.includes('resolution')"
            )
            assert not errors, errors
    _report(times, views_after, first_s)


def _report(times: list[float], views: int, first_s: float) -> None:
    median = statistics.median(times)
    print(f"\ndesigner: knob change -> histograms and previews in {median:.2f} s median "
          f"({', '.join(f'{t:.2f}' for t in times)}; {views} views, ICL living room); "
          f"page opened -> first ones in {first_s:.2f} s (cold process)")
    out = os.environ.get(RESULTS_ENV)
    if out:
        Path(out).write_text(json.dumps({
            "what": "designer page in headless Chromium, ICL living room: seconds from the last knob change "
                    "(FOV range, views per point) to updated histograms and 4 views x 4 cues of previews; "
                    "warm designer process, 200 ms input debounce included",
            "views": views, "knob_to_histograms_and_previews_s": [round(t, 3) for t in times],
            "median_s": round(median, 3), "page_open_to_first_previews_s": round(first_s, 3),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, shared with other work",
            "load_average_1m_after": round(os.getloadavg()[0], 2),
        }, indent=2) + "\n")


def test_designer_fits_b_to_the_capture_of_a_space(
    pg_url: str, local_store: LocalStore, scenes_dir: Path, tmp_path: Path, dashboard_page: DashboardPage
) -> None:
    room = scenes_dir / "icl_livingroom" / "livingroom.obj"
    parts = [("file", ("livingroom.obj", room.read_bytes())),
             ("capture", ("capture.zip", transforms_zip(tmp_path / "cap", 12)))]
    with make_api(pg_url, local_store, data_dir=str(tmp_path)) as api, live_server(api.app) as base:
        r = api.client.post("/spaces", files=parts, headers=api.a.headers)
        assert r.status_code == 201, r.text
        with dashboard_page(base, api.a.token) as (page, errors):
            page.wait_for_selector("#nav:not([hidden])")
            page.goto(f"{base}/ui/#/designer")
            page.wait_for_selector("#previews-a img", timeout=90_000)
            page.click("#design-fit")
            page.wait_for_function(
                "() => JSON.parse(document.querySelector('#previews-b')?.dataset.spec || '{}')"
                ".views?.fov_quantiles_deg?.length > 0", timeout=90_000)
            assert page.locator(".hist[data-name=fov_deg] .series-t rect").count() > 0
            assert "capture:transforms capture (12 frames)" in (page.text_content("#design-status") or "")
            assert "fov_quantiles_deg" in page.input_value("#design-yaml")
            assert not errors, errors
