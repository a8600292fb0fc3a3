"""A space whose up detection cannot decide: held as "needs frame", jobs refused with a 422 naming both
candidates, side-view PNGs of each, and the person's pick stored with the space and used by later jobs."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from services.core.db.frame_choice import space_frame_for
from services.core.db.models import Space
from services.core.domain.jobspec import JobSpec
from services.core.ingest.loading import load_space
from tests.fixtures.api import Api
from tests.fixtures.real_corpus import units_ambiguous_scan

# the BundleFusion copy room, decimated: a wall as large as the floor (see tests/fixtures/real_scans)
COPYROOM = Path(__file__).resolve().parents[2] / "fixtures" / "real_scans" / "copyroom.ply"
SPEC = {"name": "lev", "cues": ["rgb"], "points": {"count": 2, "min_views": 1}}


def _upload(api: Api) -> dict:
    r = api.client.post("/spaces", files={"file": ("copyroom.ply", COPYROOM.read_bytes())},
                        data={"name": "copyroom"}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    return r.json()


def test_ambiguous_space_held_refused_previewed_then_picked(api: Api) -> None:
    space = _upload(api)
    up = space["frame"]["up"]
    assert (space["needs_frame"] and up["ambiguous"] and up["confidence"] == "low"
            and space["up_choice"] is None)
    assert 0.5 <= up["probability"] < 0.95 and set(up["evidence"]) >= {"floor_area", "extent", "storey"}
    first, second = up["candidates"][:2]
    assert first["storey_height_m"] > 2 and second["floor_area_m2"] > 1
    assert abs(float(np.dot(first["up"], second["up"]))) < 0.2  # a wall and a floor: about 90 degrees apart

    # a job over it is refused, naming both candidates and how to pick
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": SPEC}, headers=api.a.headers)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert ("up is ambiguous" in detail and "--up=X,Y,Z" in detail
            and f"PUT /spaces/{space['id']}/up" in detail)
    assert detail.count("floor ") == detail.count("storey ") == len(up["candidates"]) >= 2
    # ... unless the spec accepts the guess
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": {**SPEC, "accept_up_guess": True}},
                        headers=api.a.headers)
    assert r.status_code == 201, r.text

    # side views: two different pictures, another tenant sees neither
    pictures = []
    for k in (0, 1):
        r = api.client.get(f"/spaces/{space['id']}/up-candidates/{k}.png", headers=api.a.headers)
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        img = np.asarray(Image.open(io.BytesIO(r.content)))
        assert img.shape == (150, 240) and (img < 200).mean() > 0.05
        pictures.append(img)
    assert (pictures[0] != pictures[1]).mean() > 0.1
    assert api.client.get(f"/spaces/{space['id']}/up-candidates/3.png",
                          headers=api.a.headers).status_code == 422
    assert api.client.get(f"/spaces/{space['id']}/up-candidates/0.png",
                          headers=api.b.headers).status_code == 404

    # the pick is stored with the space and changes its frame
    bad = api.client.put(f"/spaces/{space['id']}/up", json={"up": [0, 0, 0]}, headers=api.a.headers)
    assert bad.status_code == 422
    r = api.client.put(f"/spaces/{space['id']}/up", json={"up": second["up"]}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    picked = r.json()
    assert not picked["needs_frame"] and picked["up_axis"] == "vector"
    np.testing.assert_allclose(picked["up_choice"]["up"], second["up"], atol=1e-5)  # stored as a unit vector
    T = np.array(picked["source_to_world"])
    world_up = T[:3, :3] @ np.array(second["up"])
    assert world_up[2] > 0 and np.allclose(world_up[:2], 0, atol=1e-9)
    assert (api.client.get(f"/spaces/{space['id']}", headers=api.a.headers).json()["up_choice"]
            == picked["up_choice"])

    # later jobs are accepted and plan (and render) in the chosen frame
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": SPEC}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    with api.sessions() as s:
        row = s.get(Space, space["id"])
        assert row is not None
        frame = space_frame_for(JobSpec.model_validate(SPEC), row)
        # a spec that sets its own frame keeps it
        assert space_frame_for(JobSpec.model_validate({**SPEC, "up_axis": "+z"}), row)["up"] is None
    assert frame["up"] == picked["up_choice"]["up"]
    loaded = load_space(COPYROOM, **frame)
    np.testing.assert_allclose(loaded.source_to_world, T, atol=1e-12)


def test_a_repick_while_a_job_renders_keeps_the_planners_frame(api: Api, tmp_path: Path) -> None:
    """The planner records the frame it planned with; the job's workers load exactly that one, whatever the
    space's pick says by then (a later pick is for later jobs)."""
    from datetime import timedelta

    from services.core.db.models import Job, JobState, utcnow
    from services.core.settings import get_settings
    from services.scheduler.loop import Scheduler
    from services.scheduler.transport import NullTransport
    from services.worker.inputs.caches import TaskInputs

    space = _upload(api)
    first, second = space["frame"]["up"]["candidates"][:2]
    r = api.client.put(f"/spaces/{space['id']}/up", json={"up": second["up"]}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    planned_T = np.array(r.json()["source_to_world"])
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": SPEC}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    with api.sessions() as s:  # claim this job only (the database is shared with other tests' jobs)
        job = s.get(Job, job_id)
        assert job is not None
        job.state, job.planner, job.planner_lease_until = (JobState.PLANNING, "s17b",
                                                           utcnow() + timedelta(minutes=5))
        s.commit()
    sched = Scheduler(api.sessions, api.store, NullTransport(), get_settings(data_dir=tmp_path), "s17b")
    assert sched.plan_job(job_id)

    # the space is re-picked while the job renders
    r = api.client.put(f"/spaces/{space['id']}/up", json={"up": first["up"]}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    assert not np.allclose(np.array(r.json()["source_to_world"]), planned_T)

    inputs = TaskInputs(api.sessions, api.store, lambda fn, what: fn(), view_budget_bytes=1 << 20)
    job_info = inputs.job(job_id)
    with api.sessions() as s:
        row = s.get(Space, space["id"])
        assert row is not None
        s.expunge(row)
    frame = job_info.frame_for(row)
    np.testing.assert_allclose(frame["source_to_world"], planned_T, atol=1e-12)
    loaded = load_space(COPYROOM, **frame)  # what the worker renders: the planner's world, not the new pick
    np.testing.assert_allclose(loaded.source_to_world, planned_T, atol=1e-12)
    # a job planned now would take the new pick
    assert space_frame_for(JobSpec.model_validate(SPEC), row)["up"] == row.validation["up_choice"]["up"]
    assert not np.allclose(
        load_space(COPYROOM, **space_frame_for(JobSpec.model_validate(SPEC), row)).source_to_world, planned_T)


def test_pick_and_preview_parse_the_scan_in_the_limited_child(api: Api, monkeypatch) -> None:
    """Neither route parses the stored scan in the API process: with the parser disabled there, both still
    work."""
    import trimesh

    from services.api.spaces import up_choice

    space = _upload(api)
    second = space["frame"]["up"]["candidates"][1]

    def no_parsing_here(*_a: object, **_k: object) -> None:
        raise AssertionError("the API process parsed a scan")

    monkeypatch.setattr(trimesh, "load", no_parsing_here)
    monkeypatch.setattr("services.core.ingest.loading.load_space", no_parsing_here)
    up_choice._source_mesh.cache_clear()
    r = api.client.get(f"/spaces/{space['id']}/up-candidates/1.png", headers=api.a.headers)
    assert r.status_code == 200, r.text
    assert (np.asarray(Image.open(io.BytesIO(r.content))) < 200).mean() > 0.05
    r = api.client.put(f"/spaces/{space['id']}/up", json={"up": second["up"]}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    assert not r.json()["needs_frame"]


def test_ambiguous_units_held_refused_then_picked(api: Api, tmp_path: Path) -> None:
    """A levelled room scan in inches that too little in it tells (`units_ambiguous_scan`): cm or inches;
    the job is refused naming both."""
    src = units_ambiguous_scan(tmp_path / "partial_in.ply")
    r = api.client.post("/spaces", files={"file": ("partial_in.ply", src.read_bytes())},
                        data={"name": "partial"}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    space = r.json()
    units = space["frame"]["units"]
    assert space["needs_frame"] and units["ambiguous"] and not space["frame"]["up"].get("ambiguous")
    assert {c["unit"] for c in units["candidates"]} == {"centimetres", "inches"}
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": SPEC}, headers=api.a.headers)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert ("units are ambiguous" in detail and "--unit-scale=0.01" in detail
            and "--unit-scale=0.0254" in detail)
    assert "storey" in detail and f"PUT /spaces/{space['id']}/up" in detail
    ok = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": {**SPEC, "unit_scale": 0.01}},
                         headers=api.a.headers)
    assert ok.status_code == 201, ok.text
    r = api.client.put(f"/spaces/{space['id']}/up", json={"unit_scale": 0.01}, headers=api.a.headers)
    assert r.status_code == 200, r.text
    picked = r.json()
    assert not picked["needs_frame"] and picked["unit_scale"] == 0.01
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": SPEC}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    with api.sessions() as s:
        row = s.get(Space, space["id"])
        assert row is not None
        assert space_frame_for(JobSpec.model_validate(SPEC), row)["unit_scale"] == 0.01
