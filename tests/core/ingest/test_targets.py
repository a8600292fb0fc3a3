"""Targets to steer towards: a capture's, a point_info folder's and a CSV's distributions, against their
definitions (services.core.domain.steering)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.core.domain.plan_cues import point_info
from services.core.domain.steering import view_distributions
from services.core.ingest.capture import find_capture
from services.core.ingest.targets import TargetError, capture_target, csv_target, point_info_target
from tests.core.domain.test_steering import _plan
from tests.fixtures.captures import toy_frames, write_colmap


def test_capture_target_measures_each_camera(tmp_path: Path) -> None:
    frames = toy_frames(4)
    write_colmap(tmp_path, frames)
    capture = find_capture(tmp_path)
    assert capture is not None
    target = capture_target(capture, floor_z=0.1)
    i = np.arange(4)
    # toy cameras: 2 m from the origin at z = 0.3 + 0.1 i, looking at it, rolled by 0.05 i rad
    pitch = -np.degrees(np.arctan2(0.3 + 0.1 * i, 2.0))
    np.testing.assert_allclose(target.values["pitch_deg"], pitch, atol=1e-6)
    np.testing.assert_allclose(target.values["roll_deg"], np.degrees(0.05 * i), atol=1e-6)
    np.testing.assert_allclose(target.values["height_m"], 0.2 + 0.1 * i, atol=1e-9)
    fov = [np.degrees(f.inscribed_fov()) for f in capture.frames]
    np.testing.assert_allclose(target.values["fov_deg"], fov)
    assert target.centres is not None and target.centres.shape == (4, 3)
    assert "height_m" not in capture_target(capture, floor_z=None).values


@pytest.mark.parametrize("omnidata_keys_only", [False, True])
def test_point_info_target_matches_the_plan(tmp_path: Path, omnidata_keys_only: bool) -> None:
    plan = _plan()
    for n, view in enumerate(plan.views):
        info = dict(point_info(plan, view))
        if omnidata_keys_only:  # the public release: a Blender Euler instead of world_to_camera
            info.pop("world_to_camera")
        (tmp_path / f"point_{n}_view_0_domain_point_info.json").write_text(json.dumps(info))
    target = point_info_target(tmp_path).values
    order = sorted(range(len(plan.views)), key=lambda n: f"point_{n}_view_0")
    expected = view_distributions(plan)  # floor: the plan's lowest point, as the folder's
    for name in ("fov_deg", "pitch_deg", "roll_deg", "height_m", "distance_m"):
        np.testing.assert_allclose(target[name], expected[name][order], atol=1e-6, err_msg=name)


def test_csv_target_reads_the_known_columns(tmp_path: Path) -> None:
    path = tmp_path / "cams.csv"
    path.write_text("name,fov_deg,pitch_deg\na,60,-10\nb,70,\n")
    values = csv_target(path).values
    assert sorted(values) == ["fov_deg", "pitch_deg"]
    np.testing.assert_array_equal(values["fov_deg"], [60.0, 70.0])
    np.testing.assert_array_equal(values["pitch_deg"], [-10.0])
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(TargetError, match="no column"):
        csv_target(tmp_path / "bad.csv")
    with pytest.raises(TargetError, match="no point_info"):
        point_info_target(tmp_path)
