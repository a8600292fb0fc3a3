"""Points of interest: line of sight against brute force, min views, the try budget, Embree."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from services.core.domain.jobspec import CameraSpec, JobSpec, PointSpec
from services.core.domain.plan import PlanError
from services.scheduler.planning import make_plan
from services.scheduler.planning.cameras import generate_cameras
from services.scheduler.planning.points import sample_points, visibility_matrix
from services.scheduler.planning.visibility import MeshQueries, require_embree
from tests.fixtures import scenes

CAMS = CameraSpec(max_count=40, min_spacing_m=0.7)


@pytest.mark.parametrize("name", ["pillar_room", "l_room"])
def test_line_of_sight_matches_brute_force(name: str) -> None:
    mesh = getattr(scenes, name)()
    q = MeshQueries(mesh)
    rng = np.random.default_rng(8)
    cams = generate_cameras(q, CAMS, rng)
    spec = PointSpec(count=60, min_views=3)
    pts = sample_points(q, cams, spec, 60, rng)
    assert len(pts.positions) == 60 and pts.shortfall is None
    tol = max(spec.los_tolerance_m, 1e-5 * mesh.scale)
    origins = np.tile(cams, (60, 1))
    targets = np.repeat(pts.positions, len(cams), axis=0)
    truth = scenes.brute_force_visible(mesh, origins, targets, tol).reshape(60, len(cams))
    for i, seen in enumerate(pts.visible):
        np.testing.assert_array_equal(seen, np.flatnonzero(truth[i]))
        assert len(seen) >= 3
    # the scene has occlusion to test: in these rooms some pairs are blocked
    assert not truth.all()


def test_pillar_occlusion_is_analytic() -> None:
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    cam = np.array([[2.0, 2.0, 1.0]])
    behind = np.array([[6.0, 2.0, 1.0], [6.0, 2.1, 0.5], [6.0, 1.2, 1.0]])  # wall points behind / beside it
    seen = visibility_matrix(q, cam, behind, 0.001)[:, 0]
    # the pillar spans y 1.7..2.3 at x 3.7..4.3: rays to y=2.0 and y=2.1 cross it, y=1.2 passes by
    np.testing.assert_array_equal(seen, [False, False, True])


def test_normals_face_the_cameras_that_see_them() -> None:
    mesh = scenes.box_room()
    q = MeshQueries(mesh)
    rng = np.random.default_rng(2)
    cams = generate_cameras(q, CAMS, rng)
    pts = sample_points(q, cams, PointSpec(count=50), 50, rng)
    for p, n, seen in zip(pts.positions, pts.normals, pts.visible, strict=True):
        assert np.linalg.norm(n) == pytest.approx(1.0)
        assert ((cams[seen] - p) @ n > 0).all()
    # and points lie on the surface
    assert scenes.brute_force_distance(mesh, pts.positions).max() < 1e-9


def test_try_budget_returns_a_shortfall_quickly() -> None:
    # a small room and, far outside it, a huge closed box: almost all surface area is invisible
    room = scenes.box_room(size=(3.0, 3.0, 2.5))
    hidden = trimesh.creation.box(extents=(60.0, 60.0, 60.0))
    hidden.apply_translation([200.0, 0.0, 30.0])
    mesh = trimesh.util.concatenate([room, hidden])
    q = MeshQueries(mesh)
    cams = np.array([[1.0, 1.0, 1.2], [2.0, 1.0, 1.2], [1.5, 2.0, 1.2], [1.0, 2.2, 1.5]])
    spec = PointSpec(count=200, min_views=3, max_tries_per_point=5)
    pts = sample_points(q, cams, spec, 200, np.random.default_rng(0))
    assert pts.samples_drawn <= 200 * 5  # bounded by the budget, not an endless loop
    assert len(pts.positions) < 200
    assert pts.shortfall is not None
    assert pts.shortfall.startswith(
        f"space yields {len(pts.positions)} of 200 requested points with >= 3 views"
    )


def test_too_few_cameras_refused_up_front() -> None:
    spec = JobSpec.model_validate({
        "cameras": {"mode": "generate", "max_count": 2, "min_spacing_m": 1.0},
        "points": {"count": 10, "min_views": 3},
    })
    with pytest.raises(PlanError, match="has 2 cameras .* points.min_views is 3"):
        make_plan(scenes.as_space(scenes.box_room()), spec, np.random.default_rng(0), "room")


def test_embree_is_required() -> None:
    mesh = scenes.box_room()
    require_embree(mesh)  # the real backend passes
    slow = scenes.box_room()
    slow.ray = trimesh.ray.ray_triangle.RayMeshIntersector(slow)
    with pytest.raises(PlanError, match="needs Embree.*embreex"):
        MeshQueries(slow)
