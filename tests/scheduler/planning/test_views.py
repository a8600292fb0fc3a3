"""Wide-baseline views: fixation, fov/roll distributions, obliqueness, max views, nonfixated pruning."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from services.core.domain.camera import intrinsics, look_at, project
from services.core.domain.jobspec import CameraSpec, JobSpec, PointSpec, ViewSpec
from services.scheduler.planning import make_plan
from services.scheduler.planning.cameras import generate_cameras
from services.scheduler.planning.points import sample_points
from services.scheduler.planning.views import look_at_batch, nonfixated_keep, truncated_normal, wide_baseline
from services.scheduler.planning.visibility import MeshQueries
from tests.fixtures import scenes


@pytest.fixture(scope="module")
def sampled():
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    rng = np.random.default_rng(21)
    cams = generate_cameras(q, CameraSpec(max_count=30, min_spacing_m=0.8), rng)
    pts = sample_points(q, cams, PointSpec(count=80), 80, rng)
    return cams, pts


def test_look_at_batch_equals_camera_look_at() -> None:
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(50, 3))
    tgt = rng.normal(size=(50, 3))
    tgt[:3] = pos[:3] + [[0, 0, 2.0], [0, 0, -1.5], [0, 0, 0.3]]  # straight up/down: the fallback axis
    roll = rng.uniform(-1, 1, 50)
    W = look_at_batch(pos, tgt, roll)
    for i in range(50):
        np.testing.assert_allclose(W[i], look_at(pos[i], tgt[i], roll[i]), atol=1e-14)


def test_every_view_is_fixated_and_oblique_as_computed(sampled) -> None:
    cams, pts = sampled
    spec = ViewSpec(resolution=384)
    views = wide_baseline(pts.positions, pts.normals, pts.visible, cams, spec, None, np.random.default_rng(1))
    assert len(views) == sum(len(v) for v in pts.visible)  # one view per visible pair
    for i in range(len(views)):
        p = pts.positions[views.point_idx[i]]
        K = intrinsics(float(views.fov[i]), 384)
        uv, z = project(p[None], K, views.world_to_camera[i])
        assert np.abs(uv[0] - 192.0).max() < 1e-6 and z[0] > 0
        c = cams[views.camera_idx[i]]
        np.testing.assert_allclose(np.linalg.inv(views.world_to_camera[i])[:3, 3], c, atol=1e-12)
        d = (c - p) / np.linalg.norm(c - p)
        n = pts.normals[views.point_idx[i]]
        assert views.obliqueness[i] == pytest.approx(np.arccos(np.clip(n @ d, -1, 1)), abs=1e-12)
    # v runs 0..n-1 within each point, in order
    for p in range(len(pts.positions)):
        np.testing.assert_array_equal(views.v[views.point_idx == p], np.arange(len(pts.visible[p])))


def test_max_views_picks_a_subset_of_the_visible_cameras(sampled) -> None:
    cams, pts = sampled
    views = wide_baseline(
        pts.positions, pts.normals, pts.visible, cams, ViewSpec(), 3, np.random.default_rng(2)
    )
    for p, seen in enumerate(pts.visible):
        chosen = views.camera_idx[views.point_idx == p]
        assert len(chosen) == min(3, len(seen))
        assert set(chosen) <= set(seen.tolist())
    other = wide_baseline(
        pts.positions, pts.normals, pts.visible, cams, ViewSpec(), 3, np.random.default_rng(3)
    )
    assert not np.array_equal(views.camera_idx, other.camera_idx)  # chosen by the rng


def test_fov_truncated_normal_distribution() -> None:
    mean, std, lo, hi = np.radians([77.5, 15.0, 30.0, 125.0])
    x = truncated_normal(np.random.default_rng(7), mean, std, lo, hi, 20000)
    assert x.min() >= lo and x.max() <= hi
    a, b = (lo - mean) / std, (hi - mean) / std
    ref = stats.truncnorm(a, b, loc=mean, scale=std)
    assert x.mean() == pytest.approx(ref.mean(), abs=3 * ref.std() / np.sqrt(len(x)) + 1e-4)
    assert stats.kstest(x, ref.cdf).pvalue > 0.01
    # a narrow window deep in a tail still samples inside it
    tail = truncated_normal(np.random.default_rng(8), 0.0, 1.0, 6.0, 6.5, 1000)
    assert tail.min() >= 6.0 and tail.max() <= 6.5 and np.isfinite(tail).all()
    assert (truncated_normal(np.random.default_rng(9), 1.0, 0.0, 0.5, 2.0, 5) == 1.0).all()


def test_view_fov_and_roll_follow_the_spec(sampled) -> None:
    cams, pts = sampled
    spec = ViewSpec(fov_mean_deg=60, fov_std_deg=10, fov_min_deg=45, fov_max_deg=70, roll_max_deg=20)
    views = wide_baseline(pts.positions, pts.normals, pts.visible, cams, spec, None, np.random.default_rng(4))
    fov = np.degrees(views.fov)
    assert fov.min() >= 45 and fov.max() <= 70
    ref = stats.truncnorm((45 - 60) / 10, (70 - 60) / 10, loc=60, scale=10)
    assert stats.kstest(fov, ref.cdf).pvalue > 0.01
    roll = np.degrees(views.roll)
    assert roll.min() >= -20 and roll.max() <= 20
    assert stats.kstest(roll, stats.uniform(-20, 40).cdf).pvalue > 0.01
    # roll turns the camera about its optical axis away from the gravity-aligned frame
    # (x0 horizontal, y0 = z x x0 pointing down): x = cos(r) x0 + sin(r) y0
    for i in range(len(views)):
        R = views.world_to_camera[i][:3, :3]
        x0 = np.cross(R[2], [0, 0, 1.0])
        x0 /= np.linalg.norm(x0)
        y0 = np.cross(R[2], x0)
        assert y0[2] < 0  # image down is world down
        assert np.arctan2(R[0] @ y0, R[0] @ x0) == pytest.approx(views.roll[i], abs=1e-12)


def test_nonfixated_pruning_keeps_views_that_see_another_point(sampled) -> None:
    cams, pts = sampled
    spec = ViewSpec(fov_mean_deg=40, fov_std_deg=1, fov_min_deg=30, fov_max_deg=50)
    views = wide_baseline(pts.positions, pts.normals, pts.visible, cams, spec, 3, np.random.default_rng(5))
    keep = nonfixated_keep(views, pts.positions, pts.visible, 256)
    n_views = np.bincount(views.point_idx, minlength=len(pts.positions))
    for i in range(len(views)):
        c = views.camera_idx[i]
        others = [p for p in range(len(pts.positions))
                  if p != views.point_idx[i] and n_views[p] >= 2 and c in pts.visible[p]]
        K = intrinsics(float(views.fov[i]), 256)
        uv, z = (
            project(pts.positions[others], K, views.world_to_camera[i]) if others else (np.zeros((0, 2)), [])
        )
        inside = [(zz > 0) and (0 <= u < 256) and (0 <= v < 256) for (u, v), zz in zip(uv, z, strict=True)]
        assert keep[i] == any(inside)
    assert 0 < keep.sum() < len(views)  # narrow views: some are pruned, most are kept


def test_make_plan_pruning_drops_points_below_min_views() -> None:
    spec = JobSpec.model_validate({
        "cameras": {"max_count": 25, "min_spacing_m": 0.8},
        "points": {"count": 40, "min_views": 2, "max_views": 3},
        "views": {"nonfixated_pruning": True, "fov_mean_deg": 35, "fov_std_deg": 1, "fov_min_deg": 30,
                  "fov_max_deg": 40},
    })
    plan = make_plan(scenes.as_space(scenes.pillar_room()), spec, np.random.default_rng(6), "room")
    counts = np.bincount([v.point_idx for v in plan.views], minlength=len(plan.points))
    assert (counts >= 2).all()
    for p in plan.points:
        assert [v.v for v in plan.views_of(p.idx)] == list(range(len(plan.views_of(p.idx))))
    assert len(plan.points) < 40  # narrow views leave some points without enough views
    assert (
        plan.shortfall
        == f"nonfixated pruning kept {len(plan.points)} of 40 points (>= 2 views that each see another "
        "point)"
    )
