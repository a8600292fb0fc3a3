"""Trajectory views: path order, C2 spline, constant speed, fixation, smooth bounded roll, in_sight."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.camera import intrinsics, project
from services.core.jobspec import ViewSpec
from services.scheduler.planning.trajectory import arc_length_frames, camera_path, order_path, trajectory
from services.scheduler.planning.visibility import MeshQueries
from tests.scheduler import scenes


def _length(xyz: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())


def test_order_path_is_short() -> None:
    line = np.array([[x, 0.0, 1.0] for x in range(8)], dtype=float)
    perm = np.random.default_rng(0).permutation(8)
    order = order_path(line[perm])
    assert _length(line[perm][order]) == pytest.approx(7.0)
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 5, (12, 3))
    order = order_path(pts)
    assert sorted(order.tolist()) == list(range(12))
    # 2-opt: no single segment reversal shortens the path
    p = pts[order]
    best = _length(p)
    for i in range(12):
        for j in range(i + 1, 12):
            q = p.copy()
            q[i:j + 1] = q[i:j + 1][::-1]
            assert _length(q) >= best - 1e-9


def test_spline_is_c2_and_frames_evenly_spaced() -> None:
    way = np.array([[0.5, 0.5, 1.0], [2.0, 0.8, 1.4], [3.0, 2.5, 1.1], [1.0, 3.0, 1.6], [0.4, 2.0, 0.9]])
    spline, knots = camera_path(way)
    np.testing.assert_allclose(spline(knots), way, atol=1e-12)  # through every camera
    eps = 1e-7
    for k in knots[1:-1]:  # second derivative continuous at the interior knots (C2)
        np.testing.assert_allclose(spline(k - eps, 2), spline(k + eps, 2), atol=1e-5)
        np.testing.assert_allclose(spline(k - eps, 1), spline(k + eps, 1), atol=1e-6)
    t = arc_length_frames(spline, knots, 0.05, 10_000)
    frames = spline(t)
    step = np.linalg.norm(np.diff(frames, axis=0), axis=1)
    assert np.abs(step - 0.05).max() < 0.05 * 0.01  # constant speed: chords within 1 % of the spacing
    np.testing.assert_allclose(frames[0], way[0], atol=1e-12)
    capped = spline(arc_length_frames(spline, knots, 0.05, 40))
    assert len(capped) == 40
    np.testing.assert_allclose(capped[-1], way[-1], atol=1e-9)  # the cap spreads frames over the whole path
    cstep = np.linalg.norm(np.diff(capped, axis=0), axis=1)
    assert cstep.max() / cstep.min() < 1.02


def test_trajectory_frames_fixated_smooth_and_in_sight() -> None:
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    cams = np.array([[1.0, 1.0, 1.2], [2.0, 3.0, 1.5], [5.0, 3.2, 1.0], [5.2, 0.8, 1.4], [2.5, 0.6, 1.8]])
    point = np.array([[6.0, 2.0, 1.3]])  # on the +x wall, behind the pillar for some of the path
    normal = np.array([[-1.0, 0.0, 0.0]])
    visible = (np.arange(len(cams)),)
    spec = ViewSpec(mode="trajectory", trajectory_spacing_m=0.05, roll_max_deg=10, resolution=256)
    views = trajectory(point, normal, visible, cams, spec, None, q, 0.001, np.random.default_rng(3))
    n = len(views)
    assert n > 50
    np.testing.assert_array_equal(views.v, np.arange(n))
    pos = np.array([np.linalg.inv(W)[:3, 3] for W in views.world_to_camera])
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert np.abs(step - 0.05).max() < 0.05 * 0.01
    for i in range(n):
        uv, z = project(point, intrinsics(float(views.fov[i]), 256), views.world_to_camera[i])
        assert np.abs(uv[0] - 128.0).max() < 1e-6 and z[0] > 0
    assert len(np.unique(views.fov)) == 1  # one zoom per clip
    roll = views.roll
    assert np.abs(roll).max() <= np.radians(10) + 1e-12
    assert np.abs(np.diff(roll, 2)).max() < 1e-3  # smooth: tiny second differences at 5 cm steps
    # in_sight is the exact line of sight; the pillar hides the point from part of the path
    truth = scenes.brute_force_visible(mesh, pos, np.repeat(point, n, axis=0), max(0.001, 1e-5 * mesh.scale))
    np.testing.assert_array_equal(views.in_sight, truth)
    assert truth.any() and not truth.all()
    # camera_idx is the nearest camera
    nearest = np.linalg.norm(pos[:, None] - cams[None], axis=2).argmin(axis=1)
    np.testing.assert_array_equal(views.camera_idx, nearest)


def test_single_camera_gives_one_frame() -> None:
    q = MeshQueries(scenes.box_room())
    cams = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]])
    views = trajectory(np.array([[6.0, 2.0, 1.0]]), np.array([[-1.0, 0, 0]]), (np.array([1]),), cams,
                       ViewSpec(mode="trajectory"), None, q, 0.001, np.random.default_rng(0))
    assert len(views) == 1 and views.camera_idx[0] == 1
    np.testing.assert_allclose(np.linalg.inv(views.world_to_camera[0])[:3, 3], cams[1], atol=1e-12)
