"""`omnidata generate` on a scan with its capture beside it, as a user runs it: the capture travels with the
scan into the object store, the workers take rgb from the photos, and job.json / the manifest carry the
capture."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.core.domain.camera import intrinsics
from services.core.domain.plan import plan_from_json
from services.core.ingest.capture.photos import load_photo
from services.core.ingest.capture.resample import photo_for_view
from tests.fixtures.cli import omnidata

pytestmark = [pytest.mark.slow, pytest.mark.bpy]


def test_generate_capture_views_from_a_folder(banana_capture_folder, tmp_path: Path) -> None:
    folder, space, _ = banana_capture_folder
    spec = tmp_path / "capture.yaml"
    spec.write_text("cameras: {mode: capture}\nviews: {resolution: 48}\n")
    out = tmp_path / "out"
    res = omnidata(
        "generate", folder, "--out", out, "--spec", spec, "--cues", "rgb,depth_zbuffer,mask_photo,point_info",
        "--workers", 1, "--no-progress", timeout=600,
    )
    assert res.returncode == 0, res.stderr
    job = json.loads((out / "job.json").read_text())
    record = job["spaces"]["banana_capture"]
    assert record["capture"]["format"] == "colmap" and record["capture"]["frames"] == 3
    assert record["capture_plan"]["alignment"]["scored"] == 3
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert len(lines) == 3 and all("alignment" in x and "mask_photo" in x["outputs"] for x in lines)
    from services.datasets import OmnidataDataset

    item = OmnidataDataset(out, ["rgb", "mask_photo"])[0]  # the dataset reader decodes the new mask
    assert item["mask_photo"].dtype == bool and item["mask_photo"].all()
    plan = plan_from_json((out / "_plan" / "banana_capture.json").read_bytes())
    for view in plan.views:
        # the rgb file is exactly the photo resampled to the view (nothing of the mesh texture in it), decoded
        # no larger than the 48 px view needs
        frame = space.capture.frames[view.camera_idx]
        K = intrinsics(view.fov, 48)
        photo = load_photo(str(space.capture.image_path(frame)), frame, float(K[0, 0]))
        want, _ = photo_for_view(photo, frame, K, view.world_to_camera, 48, 48)
        got = np.array(Image.open(out / "rgb" / "omnidata" / "banana_capture" /
                                  f"point_{view.point_idx}_view_{view.v}_domain_rgb.png"))
        np.testing.assert_array_equal(got, want)
        info = json.loads((out / "point_info" / "omnidata" / "banana_capture" /
                           f"point_{view.point_idx}_view_{view.v}_domain_point_info.json").read_text())
        assert info["alignment_score"] == pytest.approx(view.alignment)
