"""Where a turned cloud's camera looked (`up_evidence`'s `camera_looked_down`, `camera_place`): a capture
whose camera, at its origin, looked down at everything it saw from a hand's height is levelled on that floor,
not on its mirror image, and only where the camera's place singles that floor out. Real clouds from
shared/rooms_held_out, turned and read by the loader that runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from services.core.ingest.errors import UpAmbiguous
from services.core.ingest.loading import load_space
from tests.fixtures.rotation_corpus import up_error_deg

REPO = Path(__file__).resolve().parents[3]
ROOMS = json.loads((REPO / "bench" / "scans" / "rooms" / "truth.json").read_text())
Z = np.array([0.0, 0.0, 1.0])

pytestmark = [pytest.mark.slow]


def _turned(name: str, euler_deg: list[float], per_metre: float, folder: Path) -> tuple[Path, np.ndarray]:
    """The room's cloud turned (xyz Euler angles) and written in 1/per_metre metres; its true up so turned."""
    room = ROOMS[name]
    R = Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()
    path = folder / f"{name}_{per_metre:g}.ply"
    trimesh.PointCloud(np.asarray(trimesh.load(REPO / room["file"]).vertices) @ R.T * per_metre).export(path)
    return path, R @ np.asarray(room["up"], dtype=float)


@pytest.mark.parametrize("per_metre", [1.0, 1000.0])
def test_a_fragment_its_camera_looked_down_at_is_levelled_turned(tmp_path: Path, per_metre: float) -> None:
    """A 3DMatch fragment (GeoTransformer's demo, held-out set 2): a floor and a desk, no ceiling, its camera
    1.3 m over the floor looking 23 degrees down. Turned, its cloud's sides alone would leave its floor and
    its mirror image 0.3 apart (asked); the camera's place levels it, in metres and in millimetres."""
    path, up = _turned("geotransformer_3dmatch_demo_ref", [-60.79, 25.96, 10.08], per_metre, tmp_path)
    space = load_space(path, cloud_cache_dir=tmp_path / "meshed")
    assert up_error_deg(space.source_to_world[:3, :3] @ up, Z) < 3.0, space.frame_summary()
    assert "the camera looked down at it" in space.frame_record()["up"]["reason"]
    assert space.units is not None and space.units.scale == pytest.approx(1.0 / per_metre)


@pytest.mark.parametrize(("name", "euler_deg", "per_metre"), [
    # a level Kinect v2 frame (ESANet's lounge): a side wall seen aslant lies wholly below the camera, which
    # looked level across the floor
    ("esanet_kinect2_lounge_frame", [-46.18, 13.73, -57.39], 1.0),
    # a hotel fragment cut to a cube: in centimetres its camera is 3.6 m over its floor read in inches and
    # 2.9 m from its largest wall, which it looked down at as it did at the floor
    ("regtr_sun3d_hotel3_frag15", [170.5, 13.61, 66.3], 100.0),
])
def test_a_camera_that_singles_out_no_floor_levels_nothing(tmp_path: Path, name: str, euler_deg: list[float],
                                                          per_metre: float) -> None:
    """Where the camera looked down at a wall as it did at the floor, or looked level across the floor, its
    place tells nothing: the scan is refused or levelled right, never planned on the wall."""
    path, up = _turned(name, euler_deg, per_metre, tmp_path)
    try:
        space = load_space(path, cloud_cache_dir=tmp_path / "meshed")
    except UpAmbiguous:
        return  # asked, not planned on a guess
    assert up_error_deg(space.source_to_world[:3, :3] @ up, Z) < 3.0, space.frame_summary()
