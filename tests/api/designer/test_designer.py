"""Designer routes on the ICL living room: a spec's plan report, its YAML both ways, previews, refusals,
tenants."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.api.designer import pool as pool_module
from services.core.storage import LocalStore
from tests.conftest import REPO_ROOT
from tests.fixtures.api import Api, make_api
from tests.fixtures.captures import transforms_zip

SMALL = {
    "points": {"count": 20, "max_views": 5},
    "views": {"fov_mean_deg": 50.0, "fov_min_deg": 40.0, "fov_max_deg": 60.0},
}


@pytest.fixture()
def room_api(
    pg_url: str, local_store: LocalStore, tmp_path: Path, scenes_dir: Path
) -> Iterator[tuple[Api, int]]:
    """The API with the ICL living room uploaded by tenant a; (api, space id)."""
    with make_api(pg_url, local_store, data_dir=str(tmp_path / "data")) as api:
        room = scenes_dir / "icl_livingroom" / "livingroom.obj"
        r = api.client.post(
            "/spaces", files={"file": ("livingroom.obj", room.read_bytes())}, headers=api.a.headers
        )
        assert r.status_code == 201, r.text
        yield api, int(r.json()["id"])


def test_plan_report_yaml_both_ways_and_previews(room_api: tuple[Api, int]) -> None:
    api, space = room_api
    r = api.client.post("/designer/plan", json={"space_ids": [space], "spec": SMALL}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    report = r.json()
    views = report["spaces"][0]["counts"]["views"]
    assert 0 < views <= 100 and report["spaces"][0]["cameras"] and report["spaces"][0]["points"]
    assert set(report["histograms"]) == {
        "fov_deg",
        "pitch_deg",
        "roll_deg",
        "height_m",
        "distance_m",
        "obliqueness_deg",
        "views_per_point",
    }
    fov = report["histograms"]["fov_deg"]
    assert sum(fov["counts"]) == views == report["summary"]["fov_deg"]["n"]
    assert all(c == 0 for e, c in zip(fov["edges"], fov["counts"], strict=False) if e < 37.5 or e >= 60)
    assert (
        max(
            report["histograms"]["views_per_point"]["edges"][i]
            for i, c in enumerate(report["histograms"]["views_per_point"]["counts"])
            if c
        )
        <= 5
    )
    assert "fov_min_deg: 40.0" in report["yaml"] and report["spec"] == SMALL

    again = api.client.post(
        "/designer/plan", json={"space_ids": [space], "spec_yaml": report["yaml"]}, headers=api.a.headers
    )
    assert again.status_code == 200, again.text
    assert again.json()["spec"] == SMALL and again.json()["histograms"] == report["histograms"]

    r = api.client.post(
        "/designer/previews", json={"space_ids": [space], "spec": SMALL, "previews": 2}, headers=api.a.headers
    )
    assert r.status_code == 200, r.text
    previews = r.json()["previews"]
    assert len(previews) == 2 and all(40 <= p["fov_deg"] <= 60 for p in previews)
    assert all(set(p["images"]) == {"rgb", "depth_zbuffer", "normal", "segment_unsup2d"} for p in previews)
    assert all(url.startswith("data:image/png;base64,") for p in previews for url in p["images"].values())


@pytest.mark.parametrize(
    ("body", "says"),
    [
        ({"spec": {"views": {"fov_min_deg": "wide"}}}, "fov_min_deg"),
        ({"spec_yaml": "views:\n  resolution: 1\n"}, "resolution"),
        ({"spec_yaml": "views: [1, 2"}, "not YAML"),
        ({"spec_yaml": "a: &x [1]\nb: *x\n"}, "aliases"),
        ({"spec_yaml": "- 1\n"}, "mapping"),
        ({"spec": {}, "spec_yaml": "{}"}, "not both"),
        ({"spec": {"points": {"count": 100_000, "max_views": 100}}}, "OMNIDATA_DESIGNER_TIMEOUT_S"),
    ],
)
def test_a_bad_spec_is_422_with_the_message(room_api: tuple[Api, int], body: dict, says: str) -> None:
    api, space = room_api
    r = api.client.post("/designer/plan", json={"space_ids": [space], **body}, headers=api.a.headers)
    assert r.status_code == 422, r.text
    assert says in r.json()["detail"]


def test_several_spaces_are_planned_and_their_views_pooled(
    room_api: tuple[Api, int], scenes_dir: Path
) -> None:
    api, space = room_api
    room = scenes_dir / "icl_livingroom" / "livingroom.obj"
    r = api.client.post(
        "/spaces",
        files={"file": ("livingroom.obj", room.read_bytes())},
        data={"name": "room2"},
        headers=api.a.headers,
    )
    assert r.status_code == 201, r.text
    ids = [space, int(r.json()["id"])]
    r = api.client.post("/designer/plan", json={"space_ids": ids, "spec": SMALL}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    report = r.json()
    assert [s["id"] for s in report["spaces"]] == ids
    assert report["summary"]["fov_deg"]["n"] == sum(s["counts"]["views"] for s in report["spaces"])
    r = api.client.post("/designer/plan", json={"space_ids": [space, space]}, headers=api.a.headers)
    assert r.status_code == 422 and "each space once" in r.json()["detail"]


def test_a_spec_is_fitted_to_the_capture_uploaded_with_the_scan(
    room_api: tuple[Api, int], scenes_dir: Path, tmp_path: Path
) -> None:
    api, bare = room_api
    room = scenes_dir / "icl_livingroom" / "livingroom.obj"
    parts = [("file", ("livingroom.obj", room.read_bytes())),
             ("capture", ("capture.zip", transforms_zip(tmp_path / "cap", 12)))]
    r = api.client.post("/spaces", files=parts, data={"name": "room_cap"}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    spec = {"points": {"count": 30, "max_views": 5}}
    r = api.client.post(
        "/designer/fit", json={"space_ids": [r.json()["id"]], "spec": spec}, headers=api.a.headers
    )
    assert r.status_code == 200, r.text
    fit = r.json()
    assert fit["source"] == "capture:transforms" and fit["frames"] == 12
    assert sum(fit["target"]["fov_deg"]["counts"]) == 12
    assert set(fit["ks"]) <= {"fov_deg", "pitch_deg", "height_m", "roll_deg"}
    assert fit["spec"]["views"]["fov_quantiles_deg"] and fit["spec"]["points"] == spec["points"]
    assert "fov_quantiles_deg" in fit["yaml"]
    r = api.client.post("/designer/fit", json={"space_ids": [bare]}, headers=api.a.headers)
    assert r.status_code == 422 and "no posed capture" in r.json()["detail"]


def test_another_tenants_space_and_an_unknown_one_are_404(room_api: tuple[Api, int]) -> None:
    api, space = room_api
    for route in ("/designer/plan", "/designer/previews", "/designer/fit"):
        r = api.client.post(route, json={"space_ids": [space]}, headers=api.b.headers)
        assert r.status_code == 404, r.text
        r = api.client.post(route, json={"space_ids": [space + 10_000]}, headers=api.a.headers)
        assert r.status_code == 404, r.text
    assert api.client.post("/designer/plan", json={"space_ids": [space]}).status_code == 401


def test_a_tenant_over_its_design_slots_gets_429_and_the_other_does_not(room_api: tuple[Api, int]) -> None:
    api, space = room_api
    throttle = api.app.state.throttle
    for _ in range(throttle.limits["design"].concurrent):
        throttle.enter("design", api.a.name)
    r = api.client.post("/designer/plan", json={"space_ids": [space]}, headers=api.a.headers)
    assert r.status_code == 429 and r.headers["Retry-After"]
    r = api.client.post("/designer/plan", json={"space_ids": [space]}, headers=api.b.headers)
    assert r.status_code == 404  # b passes the throttle (and does not see a's space)


def test_a_plan_past_the_time_budget_is_ended_and_the_api_stays_up(
    pg_url: str, local_store: LocalStore, tmp_path: Path, scenes_dir: Path
) -> None:
    with make_api(pg_url, local_store, data_dir=str(tmp_path), designer_timeout_s=0.05) as api:
        room = scenes_dir / "icl_livingroom" / "livingroom.obj"
        r = api.client.post(
            "/spaces", files={"file": ("livingroom.obj", room.read_bytes())}, headers=api.a.headers
        )
        r = api.client.post("/designer/plan", json={"space_ids": [r.json()["id"]]}, headers=api.a.headers)
        assert r.status_code == 422 and "took longer than 0.05 s" in r.json()["detail"], r.text
        assert api.client.get("/health").status_code == 200
        assert not [c for c in api.app.state.designer._children if c.alive()]


def test_the_api_process_imports_neither_the_planner_nor_blender() -> None:
    code = (
        "import sys, services.api.app; bad = [m for m in sys.modules if m.split('.')[0] == 'bpy' or "
        "m.startswith(('services.scheduler', 'services.worker', 'services.embedded'))]; print(bad); "
        "sys.exit(1 if bad else 0)"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_crashed_designer_process_is_503_with_retry_after(
    pg_url: str, local_store: LocalStore, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(pool_module, "TARGET", "tests.api.designer.fake_design:crash")
    bunny = REPO_ROOT / "examples" / "scans" / "stanford_bunny" / "bun_zipper_res2.ply"
    with make_api(pg_url, local_store, data_dir=str(tmp_path)) as api:
        upload = {"file": (bunny.name, bunny.read_bytes())}
        r = api.client.post("/spaces", files=upload, headers=api.a.headers)
        assert r.status_code == 201, r.text
        r = api.client.post("/designer/plan", json={"space_ids": [r.json()["id"]]}, headers=api.a.headers)
        assert r.status_code == 503 and r.headers["Retry-After"] == "1", r.text
        assert "process ended during a plan (exit code 3)" in r.json()["detail"]
        assert api.client.get("/health").status_code == 200
