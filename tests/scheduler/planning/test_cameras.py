"""Camera sampling: free-space Poisson disc, floors, parity, clearance, object sphere, provided poses."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import pdist

from services.core.domain.jobspec import CameraSpec
from services.core.domain.plan import PlanError
from services.scheduler.planning.cameras import (
    detect_floors,
    generate_cameras,
    inside_by_parity,
    object_cameras,
    poisson_select,
    provided_cameras,
)
from services.scheduler.planning.visibility import MeshQueries
from tests.fixtures import scenes

SPEC = CameraSpec(min_spacing_m=0.5, height_min_m=0.2, height_max_m=2.0, clearance_m=0.1, max_count=1000)


def _exact_distance(mesh: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    return scenes.brute_force_distance(mesh, pts)


def _check_cameras(mesh: trimesh.Trimesh, cams: np.ndarray, spec: CameraSpec, floor_z: float = 0.0) -> None:
    assert 0 < len(cams) <= spec.max_count
    assert pdist(cams).min() >= spec.min_spacing_m
    h = cams[:, 2] - floor_z
    assert h.min() >= spec.height_min_m and h.max() <= spec.height_max_m
    assert _exact_distance(mesh, cams).min() >= spec.clearance_m - 1e-12


@pytest.mark.parametrize("name", ["box_room", "pillar_room", "l_room"])
def test_generated_cameras_inside_clear_spaced_in_band(name: str) -> None:
    mesh = getattr(scenes, name)()
    cams = generate_cameras(MeshQueries(mesh), SPEC, np.random.default_rng(1))
    _check_cameras(mesh, cams, SPEC)
    if name == "l_room":
        assert scenes.in_l(cams).all()
        assert (cams[:, 0] > 3.0).any() and (cams[:, 1] > 3.0).any()  # both arms are used
    else:
        assert ((cams[:, :2] > 0) & (cams[:, :2] < [6.0, 4.0])).all()
    if name == "pillar_room":
        # outside the pillar (square 3.7..4.3 x 1.7..2.3) by at least the clearance
        dx = np.maximum(np.abs(cams[:, 0] - 4.0) - 0.3, 0)
        dy = np.maximum(np.abs(cams[:, 1] - 2.0) - 0.3, 0)
        assert (np.hypot(dx, dy) >= SPEC.clearance_m).all()
    # the Poisson disc nearly fills the space: a 6 x 4 x 1.8 m band holds far more than 100 cameras
    assert len(cams) > 100


def test_poisson_count_cap_and_spacing() -> None:
    mesh = scenes.box_room()
    spec = CameraSpec(max_count=10, min_spacing_m=1.0)
    cams = generate_cameras(MeshQueries(mesh), spec, np.random.default_rng(3))
    assert len(cams) == 10
    assert pdist(cams).min() >= 1.0
    pts = np.random.default_rng(0).uniform(size=(500, 3))
    keep = poisson_select(pts, 0.2, 1000)
    assert pdist(pts[keep]).min() >= 0.2
    # maximal: every rejected candidate is within the spacing of a kept one
    rejected = np.setdiff1d(np.arange(500), keep)
    d = np.linalg.norm(pts[rejected, None] - pts[keep][None], axis=2).min(axis=1)
    assert (d < 0.2).all()


def test_two_storeys_get_cameras_above_each_floor() -> None:
    lower = scenes.box_room()
    upper = scenes.box_room(origin=(0.0, 0.0, 3.0))
    mesh = trimesh.util.concatenate([lower, upper])
    floors = detect_floors(mesh)
    assert [round(f.z, 6) for f in floors] == [0.0, 3.0]
    assert [round(f.area, 6) for f in floors] == [24.0, 24.0]
    cams = generate_cameras(MeshQueries(mesh), SPEC, np.random.default_rng(2))
    low = cams[:, 2] < 2.85
    assert low.any() and (~low).any()
    _check_cameras(mesh, cams[low], SPEC, floor_z=0.0)
    _check_cameras(mesh, cams[~low], SPEC, floor_z=3.0)


def test_table_top_is_not_a_floor() -> None:
    floors = detect_floors(scenes.furnished_room())
    assert len(floors) == 1 and floors[0].z == pytest.approx(0.0)


def test_no_floor_is_refused() -> None:
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    with pytest.raises(PlanError, match="no floor found.*mode 'object'"):
        generate_cameras(MeshQueries(ball), SPEC, np.random.default_rng(0))


def test_parity_majority_survives_a_hole() -> None:
    room = scenes.box_room()
    holed = trimesh.Trimesh(room.vertices, room.faces[1:], process=False)  # one wall triangle missing
    q = MeshQueries(holed)
    rng = np.random.default_rng(5)
    inside = rng.uniform([0.2, 0.2, 0.2], [5.8, 3.8, 2.5], (400, 3))
    assert inside_by_parity(q, inside).mean() >= 0.95
    outside = rng.uniform([-3, -3, -1], [9, 7, 4], (4000, 3))
    outside = outside[~((outside > 0) & (outside < [6, 4, 2.7])).all(axis=1)][:400]
    assert inside_by_parity(q, outside).mean() <= 0.05
    full = MeshQueries(room)
    assert inside_by_parity(full, inside).all()
    assert not inside_by_parity(full, outside).any()


def test_near_mesh_is_exact_on_mixed_face_sizes() -> None:
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    ball.apply_translation([3.0, 2.0, 1.2])
    mesh = trimesh.util.concatenate([scenes.box_room(), ball])
    rng = np.random.default_rng(11)
    pts = rng.uniform([0, 0, 0], [6, 4, 2.7], (1500, 3))
    d = _exact_distance(mesh, pts)
    q = MeshQueries(mesh)
    for r in (0.05, 0.1, 0.4):
        near = q.near_mesh(pts, r)
        clear = np.abs(d - r) > 1e-9
        np.testing.assert_array_equal(near[clear], (d < r)[clear])


def test_object_cameras_exactly_on_the_sphere(shared_scenes) -> None:
    from services.core.ingest.loading import load_space

    bunny = load_space(shared_scenes / "stanford_bunny" / "bun_zipper_res2.ply").mesh
    spec = CameraSpec(mode="object", object_count=200, object_distance_factor=2.5)
    cams, centre, radius = object_cameras(bunny, spec, np.random.default_rng(4))
    sphere = bunny.bounding_sphere.primitive
    np.testing.assert_allclose(centre, sphere.center)
    assert radius == pytest.approx(2.5 * sphere.radius)
    assert len(cams) == 200
    dist = np.linalg.norm(cams - centre, axis=1)
    assert np.abs(dist - radius).max() <= 1e-12 * radius
    # evenly spread: the mean direction is near zero and nearest neighbours are alike
    u = (cams - centre) / radius
    assert np.linalg.norm(u.mean(axis=0)) < 0.02
    nn = np.sort(np.linalg.norm(u[:, None] - u[None], axis=2), axis=1)[:, 1]
    assert nn.max() / nn.min() < 1.6
    other, _, _ = object_cameras(bunny, spec, np.random.default_rng(5))
    assert not np.allclose(cams, other)  # the rng turns the lattice


def test_provided_positions_pass_through() -> None:
    spec = CameraSpec(mode="provided", poses=[{"location": (1, 2, 1.5)}, {"location": (3.5, 1, 1)}])
    np.testing.assert_array_equal(provided_cameras(spec), [[1, 2, 1.5], [3.5, 1, 1]])
