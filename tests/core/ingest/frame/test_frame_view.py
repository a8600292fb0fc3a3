"""One depth frame told from a fusion of several views by what lies behind what, seen from the origin
(services.core.ingest.frame.single_view: `occluded_share`, `frame_view`), and the planes its own points lend
where its mesh lost them (services.core.ingest.frame.gravity: `_lost_floor_axes`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from services.core.ingest.frame.gravity import _lost_floor_axes
from services.core.ingest.frame.single_view import (
    OCCLUDED_MAX_SHARE,
    SingleView,
    frame_view,
    occluded_share,
    single_view,
)
from services.core.ingest.pointcloud import cloud_from_ply

HELD_OUT = Path(__file__).resolve().parents[4] / "shared" / "rooms_held_out"


def _depth_frame(eye: np.ndarray) -> np.ndarray:
    """What a depth camera at `eye` (level axes: x right, y down, z ahead) sees of a floor 1.5 m below the
    origin, a wall 4 m ahead, a table top 0.75 m high and a cabinet's front 2 m ahead: one point per pixel
    ray, its nearest hit."""
    u, v = np.meshgrid(np.linspace(-0.55, 0.55, 160), np.linspace(-0.2, 0.6, 120))
    rays = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)])
    hits = np.full(len(rays), np.inf)
    for axis, at, inside in ((1, 1.5, lambda p: np.abs(p[:, 0]) < 2.0),  # floor
                             (2, 4.0, lambda p: np.abs(p[:, 0]) < 2.0),  # wall
                             (1, 0.75, lambda p: (np.abs(p[:, 0]) < 0.5) & (np.abs(p[:, 2] - 2.5) < 0.4)),
                             (2, 2.0, lambda p: (np.abs(p[:, 0] + 0.4) < 0.8) & (p[:, 1] > -0.5))):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (at - eye[axis]) / rays[:, axis]
        p = eye + t[:, None] * rays
        ok = (t > 0) & inside(p)
        hits[ok] = np.minimum(hits[ok], t[ok])
    seen = np.isfinite(hits)
    return eye + hits[seen, None] * rays[seen]


def test_one_depth_frame_has_nothing_behind_anything() -> None:
    frame = _depth_frame(np.zeros(3))
    assert occluded_share(frame) <= OCCLUDED_MAX_SHARE
    assert frame_view(frame) is not None


def test_a_fusion_of_two_views_holds_what_the_other_camera_saw_behind() -> None:
    """A second camera 1.5 m to the side sees wall and floor the cabinet hides from the first: from the
    origin they lie behind the cabinet, so the two fused are one frustum (`single_view`) but not one frame."""
    fused = np.vstack([_depth_frame(np.zeros(3)), _depth_frame(np.array([1.5, 0.0, 0.0]))])
    assert single_view(fused) is not None
    assert occluded_share(fused) > OCCLUDED_MAX_SHARE
    assert frame_view(fused) is None


def _held_out(name: str) -> np.ndarray:
    path = HELD_OUT / name / f"{name}.ply"
    return cloud_from_ply(trimesh.load(path)).points


@pytest.mark.parametrize("name", ["sscnet_nyu0001_frame", "open3d_sun3d_office_corridor",
                                  "threedmatch_toolbox_single_depth1"])
def test_real_depth_frames_are_one_frame(name: str) -> None:
    assert frame_view(_held_out(name)) is not None


@pytest.mark.parametrize("name", ["teaser_sun3d_home_at_frag2", "geotransformer_3dmatch_demo_ref",
                                  "predator_3dmatch_demo_cloud21"])
def test_real_fusions_as_narrow_as_one_view_are_not_one_frame(name: str) -> None:
    """3DMatch fragments (50 depth frames fused) fill no more of the view than one frame does."""
    points = _held_out(name)
    assert single_view(points) is not None
    assert frame_view(points) is None


def test_a_frames_points_lend_a_plane_only_where_its_mesh_shows_none_near_its_short_side() -> None:
    """A landscape frame's up lies near its short side: where its mesh shows no plane there (a far floor lost
    to meshing), the planes read from its points that lie there are weighed too, and no others; where its
    mesh shows one, or the frame is square, its points are not read (`gravity._lost_floor_axes`)."""
    view = SingleView(direction=np.array([0.0, 0.0, 1.0]), short_axis=np.array([0.0, 1.0, 0.0]))
    floor = np.array([0.0, 0.96, 0.28])  # a camera pitched 16 degrees down sees this floor
    read: list[int] = []

    def points_planes() -> list[np.ndarray]:
        read.append(1)
        return [floor, np.array([1.0, 0.0, 0.0])]

    walls = [(np.array([1.0, 0.0, 0.0]), 5.0), (np.array([0.0, 0.0, 1.0]), 9.0)]
    added = _lost_floor_axes(walls, view, points_planes)
    assert len(added) == 1 and np.allclose(added[0], floor)
    read.clear()
    assert _lost_floor_axes([*walls, (floor, 2.0)], view, points_planes) == [] and not read
    square = SingleView(direction=view.direction, short_axis=None)
    assert _lost_floor_axes(walls, square, points_planes) == [] and not read
