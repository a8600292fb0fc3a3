"""Picking a space's up in the dashboard: the two candidates side by side with their side views, one click,
and the choice stored with the space (headless Chromium against a real uvicorn server on Postgres)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.core.storage import LocalStore
from tests.browser.conftest import DashboardPage
from tests.fixtures.api import live_server, make_api
from tests.fixtures.real_corpus import units_ambiguous_scan

pytestmark = pytest.mark.slow

COPYROOM = Path(__file__).resolve().parents[1] / "fixtures" / "real_scans" / "copyroom.ply"


def test_pick_up_with_one_click(pg_url: str, local_store: LocalStore, dashboard_page: DashboardPage,
                                artifacts: Path) -> None:
    with make_api(pg_url, local_store) as api, live_server(api.app) as base:
        r = api.client.post("/spaces", files={"file": ("copyroom.ply", COPYROOM.read_bytes())},
                            data={"name": "copyroom"}, headers=api.a.headers)
        assert r.status_code == 201, r.text
        space = r.json()
        assert space["needs_frame"]
        runner_up = space["frame"]["up"]["candidates"][1]["up"]
        with dashboard_page(base, api.a.token) as (page, errors):
            page.wait_for_selector("#needs-frame .up-candidate", timeout=30_000)
            figures = page.query_selector_all(f'#needs-frame [data-space="{space["id"]}"] .up-candidate')
            assert len(figures) == len(space["frame"]["up"]["candidates"]) >= 2
            # both side views arrive (fetched with the token) and differ
            page.wait_for_function(
                "() => [...document.querySelectorAll('#needs-frame img.up-preview')]"
                ".every((img) => img.complete && img.naturalWidth === 240)", timeout=30_000)
            captions = [f.inner_text() for f in figures]
            assert "Detection's best" in captions[0] and "Runner-up" in captions[1]
            assert all("floor" in c and "storey" in c and "extent" in c for c in captions)  # the evidence too
            page.screenshot(path=str(artifacts / "dashboard-pick-up.png"), full_page=True)
            page.click('#needs-frame button.pick-up[data-index="1"]')
            # the panel goes once picked
            page.wait_for_selector("#needs-frame", state="detached", timeout=30_000)
            assert errors == []
        stored = api.client.get(f"/spaces/{space['id']}", headers=api.a.headers).json()
        assert not stored["needs_frame"]
        np.testing.assert_allclose(stored["up_choice"]["up"], runner_up, atol=1e-5)
        r = api.client.post("/jobs",
                            json={"space_ids": [space["id"]], "spec": {"name": "lev", "cues": ["rgb"]}},
                            headers=api.a.headers)
        assert r.status_code == 201, r.text


def test_pick_units_with_one_click(pg_url: str, local_store: LocalStore, dashboard_page: DashboardPage,
                                   tmp_path: Path) -> None:
    """A levelled room scan in inches that too little in it tells (`units_ambiguous_scan`): cm or inches,
    each with the size it gives."""
    src = units_ambiguous_scan(tmp_path / "partial_in.ply")
    with make_api(pg_url, local_store) as api, live_server(api.app) as base:
        r = api.client.post("/spaces", files={"file": ("partial_in.ply", src.read_bytes())},
                            data={"name": "partial"}, headers=api.a.headers)
        assert r.status_code == 201, r.text
        space = r.json()
        assert space["needs_frame"] and space["frame"]["units"]["ambiguous"]
        with dashboard_page(base, api.a.token) as (page, errors):
            page.wait_for_selector("#needs-frame .unit-candidate", timeout=30_000)
            assert page.query_selector_all("#needs-frame .up-candidate") == []  # its up is decided
            captions = [f.inner_text() for f in page.query_selector_all("#needs-frame .unit-candidate")]
            assert any("centimetres" in c and "storey 0.81" in c for c in captions)
            assert any("inches" in c and "storey 2.07" in c for c in captions)
            page.click('#needs-frame button.pick-units[data-unit="centimetres"]')
            page.wait_for_selector("#needs-frame", state="detached", timeout=30_000)
            assert errors == []
        stored = api.client.get(f"/spaces/{space['id']}", headers=api.a.headers).json()
        assert not stored["needs_frame"] and stored["unit_scale"] == 0.01
