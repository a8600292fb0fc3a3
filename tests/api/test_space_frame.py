"""A space whose up detection cannot decide: held as "needs frame", jobs refused with a 422 naming both
candidates, side-view PNGs of each, and the person's pick stored with the space and used by later jobs."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from services.core.db.models import Space
from services.core.domain.jobspec import JobSpec
from services.core.ingest.frame_choice import space_frame_for
from services.core.ingest.loading import load_space
from tests.fixtures.api import Api

# the BundleFusion copy room, decimated: a wall as large as the floor (see tests/fixtures/real_scans)
COPYROOM = Path(__file__).resolve().parents[1] / "fixtures" / "real_scans" / "copyroom.ply"
SPEC = {"name": "lev", "cues": ["rgb"], "points": {"count": 2, "min_views": 1}}


def _upload(api: Api) -> dict:
    r = api.client.post("/spaces", files={"file": ("copyroom.ply", COPYROOM.read_bytes())}, data={"name": "copyroom"},
                        headers=api.a.headers)
    assert r.status_code == 201, r.text
    return r.json()


def test_ambiguous_space_held_refused_previewed_then_picked(api: Api) -> None:
    space = _upload(api)
    up = space["frame"]["up"]
    assert space["needs_frame"] and up["ambiguous"] and up["confidence"] == "low" and space["up_choice"] is None
    assert 0.5 <= up["probability"] < 0.95 and set(up["evidence"]) >= {"floor_area", "extent", "storey"}
    first, second = up["candidates"][:2]
    assert first["storey_height_m"] > 2 and second["floor_area_m2"] > 1
    assert abs(float(np.dot(first["up"], second["up"]))) < 0.2  # a wall and a floor: about 90 degrees apart

    # a job over it is refused, naming both candidates and how to pick
    r = api.client.post("/jobs", json={"space_ids": [space["id"]], "spec": SPEC}, headers=api.a.headers)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "up is ambiguous" in detail and "--up=X,Y,Z" in detail and f"PUT /spaces/{space['id']}/up" in detail
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
    assert api.client.get(f"/spaces/{space['id']}/up-candidates/3.png", headers=api.a.headers).status_code == 422
    assert api.client.get(f"/spaces/{space['id']}/up-candidates/0.png", headers=api.b.headers).status_code == 404

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
    assert api.client.get(f"/spaces/{space['id']}", headers=api.a.headers).json()["up_choice"] == picked["up_choice"]

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
