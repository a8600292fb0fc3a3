"""A point cloud's own planes (services.core.ingest.frame.point_planes): a cloud of edges, as SLAM gives,
shows its floor from its points, and levelling weighs them through the same decision, never wrongly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from services.core.ingest.errors import UpAmbiguous
from services.core.ingest.frame.gravity import estimate_up, plane_families
from services.core.ingest.frame.point_planes import point_samples, voxel_means
from services.core.ingest.loading import load_space
from tests.fixtures.rotation_corpus import up_error_deg


def _segment(rng: np.random.Generator, a: tuple[float, ...], b: tuple[float, ...]) -> np.ndarray:
    """Points along a straight edge from a to b, 1 cm apart on average, 5 mm of noise."""
    a_, b_ = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    n = max(2, int(np.linalg.norm(b_ - a_) / 0.01))
    return a_ + rng.random(n)[:, None] * (b_ - a_) + rng.normal(0.0, 0.005, (n, 3))


Edge = tuple[tuple[float, ...], tuple[float, ...]]


def _rectangle(corners: list[tuple[float, float, float]]) -> list[Edge]:
    return list(zip(corners, corners[1:] + corners[:1], strict=True))


def edge_room(rng: np.random.Generator, floor_line_step: float = 0.5) -> np.ndarray:
    """A 5 x 4 x 2.6 m room (+Z up, metres) as SLAM samples it: points on edges only (floor boards every
    `floor_line_step`, two tables' outlines and legs, wall corners, skirting, picture and door frames)."""
    w, d, h = 5.0, 4.0, 2.6
    edges: list[Edge] = [((x, 0.0, 0.0), (x, d, 0.0)) for x in np.arange(floor_line_step, w, floor_line_step)]
    edges += [((0.0, y, 0.0), (w, y, 0.0)) for y in np.arange(0.8, d, 0.8)]
    for x0, y0 in ((1.0, 1.0), (3.0, 2.2)):
        top = [(x0, y0, 0.75), (x0 + 1.2, y0, 0.75), (x0 + 1.2, y0 + 0.8, 0.75), (x0, y0 + 0.8, 0.75)]
        edges += _rectangle(top) + [((x, y, 0.0), (x, y, z)) for x, y, z in top]
    for y in (0.0, d):
        edges += [((0.0, y, 0.0), (0.0, y, h)), ((w, y, 0.0), (w, y, h)), ((0.0, y, 0.1), (w, y, 0.1))]
        for x in (1.0, 3.0):
            edges += _rectangle([(x, y, 1.2), (x + 0.8, y, 1.2), (x + 0.8, y, 1.8), (x, y, 1.8)])
    for x in (0.0, w):
        edges += [((x, 0.0, 0.1), (x, d, 0.1)), ((x, 1.5, 0.0), (x, 1.5, 2.0)),
                  ((x, 2.4, 0.0), (x, 2.4, 2.0)), ((x, 1.5, 2.0), (x, 2.4, 2.0))]
    return np.vstack([_segment(rng, a, b) for a, b in edges])


ROTATIONS = Rotation.random(4, random_state=7).as_matrix()


def test_voxel_means_average_each_voxel_once() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [2.0, 0.0, 0.0], [2.2, 0.4, 0.0]])
    means = voxel_means(pts, 1.0)
    assert sorted(map(tuple, np.round(means, 6))) == [(0.25, 0.25, 0.25), (2.1, 0.2, 0.0)]


@pytest.mark.parametrize("R", ROTATIONS)
def test_an_edge_only_room_shows_its_floor_family_from_its_points(R: np.ndarray) -> None:
    """The strongest plane family of the points' coarse PCA normals is the floor's, whatever the rotation;
    the voxel weights make each sample stand for the same area."""
    samples = point_samples(edge_room(np.random.default_rng(1)) @ R.T)
    assert samples is not None
    families = plane_families(samples.normals, samples.areas)
    assert up_error_deg(families[0][0], R[:, 2]) < 2.0 or up_error_deg(-families[0][0], R[:, 2]) < 2.0
    assert np.ptp(samples.areas) == 0.0


def test_a_room_edged_densely_enough_levels_from_its_points_through_the_same_decision() -> None:
    """Floor boards 10 cm apart cover the floor share a room needs: the points alone level it (the floor path
    of estimate_up, its calibrated decision), within a degree of the truth."""
    R = ROTATIONS[0]
    samples = point_samples(edge_room(np.random.default_rng(2), floor_line_step=0.1) @ R.T)
    assert samples is not None
    est = estimate_up(trimesh.creation.box(), ".ply", samples=samples)  # the samples stand for the mesh
    assert est.method == "floor" and est.decision is not None and not est.ambiguous
    assert up_error_deg(est.up, R[:, 2]) < 1.0


def test_a_rotated_edge_only_cloud_is_refused_with_its_true_up_first(tmp_path: Path) -> None:
    """Through load_space (meshed by screened Poisson, as ingest does): sparse edges give no floor share, so
    nothing is levelled on a guess; the refusal offers the true up first."""
    R = ROTATIONS[1]
    cloud = tmp_path / "edges.ply"
    trimesh.PointCloud(edge_room(np.random.default_rng(3)) @ R.T).export(cloud)
    with pytest.raises(UpAmbiguous) as refused:
        load_space(cloud, cloud_cache_dir=tmp_path / "meshed")
    assert up_error_deg(np.asarray(refused.value.candidates[0]["up"], dtype=float), R[:, 2]) < 3.0

