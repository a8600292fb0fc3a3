"""Per-vertex principal curvature against surfaces of known curvature."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from services.core.ingest.loading import load_space
from services.worker.inputs import curvature
from services.worker.inputs.curvature import principal_curvatures
from tests.fixtures import reference_curvature


def tube(radius: float, length: float, sections: int = 128, rings: int = 81) -> trimesh.Trimesh:
    """An open cylinder along z with a regular grid of vertices (outward normals)."""
    th = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    zs = np.linspace(-length / 2, length / 2, rings)
    T, Z = np.meshgrid(th, zs)
    V = np.stack([radius * np.cos(T), radius * np.sin(T), Z], axis=-1).reshape(-1, 3)
    faces = []
    for i in range(rings - 1):
        for j in range(sections):
            a, b = i * sections + j, i * sections + (j + 1) % sections
            faces += [[a, b, b + sections], [a, b + sections, a + sections]]
    return trimesh.Trimesh(V, np.array(faces), process=False)


@pytest.mark.parametrize("r", [0.5, 2.0])
def test_sphere_has_k1_equal_k2_equal_inverse_radius(r: float) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    k = principal_curvatures(sphere, radius=0.2 * r)
    assert k.shape == (len(sphere.vertices), 2) and k.dtype == np.float32
    np.testing.assert_allclose(np.median(k, axis=0), [1 / r, 1 / r], rtol=0.03)
    assert np.percentile(np.abs(k - 1 / r), 95) < 0.08 / r


def test_inward_normals_flip_the_sign() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    sphere.invert()
    k = principal_curvatures(sphere, radius=0.2)
    np.testing.assert_allclose(np.median(k, axis=0), [-1.0, -1.0], rtol=0.05)


def test_cylinder_has_k1_inverse_radius_and_k2_zero() -> None:
    r = 0.3
    cyl = tube(r, 2.0)
    k = principal_curvatures(cyl, radius=0.1)
    mid = np.abs(cyl.vertices[:, 2]) < 0.8  # away from the open ends
    np.testing.assert_allclose(np.median(k[mid, 0]), 1 / r, rtol=0.03)
    assert abs(np.median(k[mid, 1])) < 0.05 / r
    assert np.all(k[:, 0] >= k[:, 1])


def test_plane_is_flat_and_result_is_deterministic() -> None:
    xs = np.linspace(-1, 1, 41)
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X, Y, 0.02 * X + 0.01 * Y], axis=-1).reshape(-1, 3)  # a tilted plane
    faces = [[i * 41 + j, i * 41 + j + 1, (i + 1) * 41 + j + 1] for i in range(40) for j in range(40)]
    faces += [[i * 41 + j, (i + 1) * 41 + j + 1, (i + 1) * 41 + j] for i in range(40) for j in range(40)]
    plane = trimesh.Trimesh(V, np.array(faces), process=False)
    k1 = principal_curvatures(plane, radius=0.1)
    inner = np.all(np.abs(V[:, :2]) < 0.85, axis=1)
    assert np.all(np.abs(k1[inner]) < 1e-3)
    np.testing.assert_array_equal(k1, principal_curvatures(plane, radius=0.1))


def test_radius_must_be_positive() -> None:
    with pytest.raises(ValueError, match="positive"):
        principal_curvatures(trimesh.creation.icosphere(), radius=0.0)


def _noisy_dense_sphere() -> trimesh.Trimesh:
    """40,962 vertices on the unit sphere, jittered so no two samples tie in distance: ~400 in a 0.2 ball."""
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    jitter = np.random.default_rng(1).normal(0, 1e-3, sphere.vertices.shape)
    return trimesh.Trimesh(sphere.vertices + jitter, sphere.faces, process=False)


def test_a_room_is_searched_in_the_grid_and_fitted_as_the_kd_tree_queries_were(
        scenes_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same samples, nearest first, so the same sums and curvatures, bit for bit (the old estimator is
    tests/fixtures/reference_curvature.py); no k-d tree is built for a room."""
    room = load_space(scenes_dir / "icl_livingroom").mesh
    want = reference_curvature.principal_curvatures(room, 0.05)
    monkeypatch.setattr(curvature, "cKDTree", None)  # calling it would raise
    np.testing.assert_array_equal(principal_curvatures(room, 0.05), want)


def test_crowded_balls_give_the_same_curvature_by_either_search(monkeypatch: pytest.MonkeyPatch) -> None:
    """A dense mesh adds its vertices to the samples: its balls overflow the neighbour cap (96) and the grid's
    first buffer (256). It goes to the k-d tree, and the grid, made to take it, keeps the same 96 nearest."""
    dense = _noisy_dense_sphere()
    want = reference_curvature.principal_curvatures(dense, 0.2)
    np.testing.assert_array_equal(principal_curvatures(dense, 0.2), want)
    monkeypatch.setattr(curvature, "GRID_MAX_BALL", np.inf)
    monkeypatch.setattr(curvature, "cKDTree", None)
    np.testing.assert_array_equal(principal_curvatures(dense, 0.2), want)


def test_surface_samples_are_numpys_expression_on_the_gathered_triangles_bit_for_bit(
    scenes_dir: Path,
) -> None:
    room = load_space(scenes_dir / "icl_livingroom").mesh
    pts, fidx = curvature._sample_surface(room, 50_000, np.random.default_rng(4))
    rng = np.random.default_rng(4)  # the same draws, in the same order, through the expression it replaced
    area = np.asarray(room.area_faces, dtype=np.float64)
    cdf = np.cumsum(area)
    want_f = np.searchsorted(cdf, rng.random(50_000) * cdf[-1], side="right").clip(0, len(area) - 1)
    tri = np.asarray(room.triangles, dtype=np.float64)[want_f]
    r1, r2 = rng.random(50_000), rng.random(50_000)
    flip = r1 + r2 > 1.0
    r1[flip], r2[flip] = 1.0 - r1[flip], 1.0 - r2[flip]
    want = tri[:, 0] + r1[:, None] * (tri[:, 1] - tri[:, 0]) + r2[:, None] * (tri[:, 2] - tri[:, 0])
    assert flip.any() and np.array_equal(fidx, want_f)
    assert pts.tobytes() == want.tobytes()
