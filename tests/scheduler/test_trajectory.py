"""Trajectory views: free-space routes, curvature-bounded smoothing, verified frames, limits, notes."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from services.core.camera import camera_center, intrinsics, project
from services.core.jobspec import JobSpec, ViewSpec
from services.core.plan import SpacePlan, plan_from_json, plan_to_json
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.trajectory import (
    Limits,
    fly_clip,
    free_space_graph,
    longest_run,
    resample,
    rotation_angles,
    smooth_path,
    trajectory,
    trim,
    turn_angles,
)
from services.scheduler.planning.visibility import MeshQueries
from tests.scheduler import scenes


def _centres(W: np.ndarray) -> np.ndarray:
    return np.stack([camera_center(w) for w in W])


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1, 1))


def test_turn_and_rotation_angles_match_direct_geometry() -> None:
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]])
    np.testing.assert_allclose(turn_angles(square), [np.pi / 2, np.pi / 2])
    rz = np.eye(4)[None].repeat(2, axis=0)
    c, s = np.cos(0.3), np.sin(0.3)
    rz[1, :2, :2] = [[c, -s], [s, c]]
    np.testing.assert_allclose(rotation_angles(rz), [0.3])


def test_smoothing_bounds_the_turn_keeps_the_ends_and_spacing() -> None:
    # a zig-zag through cameras 0.5 m apart at mixed heights: the path of the old interpolating spline
    route = np.array([[0.5 * i, 0.4 * (i % 2), 1.0 + 0.3 * ((i // 2) % 2)] for i in range(12)])
    limit = np.radians(60.0)
    smooth = smooth_path(route, 0.1, limit)
    np.testing.assert_allclose(smooth[0], route[0], atol=1e-9)
    np.testing.assert_allclose(smooth[-1], route[-1], atol=1e-6)
    frames = resample(smooth, 0.1, keep_end=False)
    step = np.linalg.norm(np.diff(frames, axis=0), axis=1)
    assert np.abs(step - 0.1).max() < 0.1 * 0.01
    assert turn_angles(frames).max() <= limit * 0.1
    assert turn_angles(resample(route, 0.1, keep_end=False)).max() > np.radians(30)  # it was zig-zag


def test_trim_keeps_the_first_metres() -> None:
    poly = np.array([[0.0, 0, 0], [1, 0, 0], [1, 2, 0]])
    np.testing.assert_allclose(trim(poly, 1.5), [[0, 0, 0], [1, 0, 0], [1, 0.5, 0]])
    np.testing.assert_allclose(trim(poly, 1.0), [[0, 0, 0], [1, 0, 0], [1, 0, 0]])
    assert trim(poly, 5.0) is poly


def test_longest_run_needs_good_frames_and_links() -> None:
    good = np.array([1, 1, 0, 1, 1, 1, 1, 0], dtype=bool)
    link = np.ones(7, dtype=bool)
    assert longest_run(good, link) == (3, 7)
    link[4] = False  # frame 4 -> 5 breaks the run
    assert longest_run(good, link) == (0, 2)
    assert longest_run(np.zeros(3, dtype=bool), np.ones(2, dtype=bool)) == (0, 0)


def test_free_space_graph_edges_are_clear() -> None:
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    rng = np.random.default_rng(0)
    cams = rng.uniform([0.3, 0.3, 0.3], [5.7, 3.7, 2.4], (60, 3))
    cams = cams[scenes.brute_force_distance(mesh, cams) >= 0.1]
    g = free_space_graph(cams, q, 0.1).tocoo()
    assert g.nnz > 0 and (g.row != g.col).all()
    np.testing.assert_allclose(g.data, np.linalg.norm(cams[g.row] - cams[g.col], axis=1))
    a, b = cams[g.row], cams[g.col]
    assert scenes.brute_force_visible(mesh, a, b, 1e-9).all()
    mid = (a + b) / 2
    assert scenes.brute_force_distance(mesh, mid).min() >= 0.1 - 0.025  # sampled every <= 5 cm
    # two cameras on either side of the pillar are never joined
    pair = np.array([[3.4, 2.0, 1.2], [4.6, 2.0, 1.2]])
    assert free_space_graph(pair, q, 0.1).nnz == 0


def _check_clip_limits(plan: SpacePlan, spec: JobSpec, mesh) -> int:
    """Assert every clip of a plan against the spec's limits by independent geometry; frames checked."""
    vs = spec.views
    checked = 0
    for point in plan.points:
        views = plan.views_of(point.idx)
        assert 1 <= len(views) <= vs.trajectory_max_frames
        W = np.stack([v.world_to_camera for v in views])
        c = _centres(W)
        if len(c) > 1:
            step = np.linalg.norm(np.diff(c, axis=0), axis=1)
            assert np.abs(step - vs.trajectory_spacing_m).max() < 0.01 * vs.trajectory_spacing_m
            assert rotation_angles(W).max() <= np.radians(vs.trajectory_max_view_deg_per_m) * step.max() + 1e-9
        if len(c) > 2:
            assert turn_angles(c).max() <= np.radians(vs.trajectory_max_turn_deg_per_m) * vs.trajectory_spacing_m + 1e-9
        assert scenes.brute_force_distance(mesh, c).min() >= spec.cameras.clearance_m
        seen = scenes.brute_force_visible(mesh, c, np.tile(point.position, (len(c), 1)), 1e-3)
        np.testing.assert_array_equal([v.in_sight for v in views], seen)
        if vs.trajectory_look == "point":
            assert seen.all()
            for i, v in enumerate(views):
                uv, z = project(point.position[None], intrinsics(v.fov, v.resolution), W[i])
                assert np.abs(uv[0] - v.resolution / 2).max() < 1e-6 and z[0] > 0
        elif len(c) > 2:  # ahead: the optical axis follows the direction of motion
            tangent = np.gradient(c, axis=0)
            assert _angle_between(W[:, 2, :3], tangent).max() < 1e-6
        assert len({v.fov for v in views}) == 1  # one zoom per clip
        roll = np.array([v.roll for v in views])
        assert np.abs(roll).max() <= np.radians(vs.roll_max_deg) + 1e-12
        checked += len(views)
    return checked


@pytest.mark.parametrize("look", ["point", "ahead"])
def test_clips_in_generated_rooms_meet_the_limits(look: str) -> None:
    spec = JobSpec.model_validate({
        "seed": 5, "points": {"count": 4},
        "views": {"mode": "trajectory", "trajectory_spacing_m": 0.1, "trajectory_max_frames": 120,
                  "trajectory_look": look, "resolution": 64},
    })
    frames = 0
    for k in range(3):
        mesh = scenes.random_furnished_room(np.random.default_rng(40 + k))
        plan = make_plan(scenes.as_space(mesh), spec, space_rng(spec.seed, f"room{k}"), f"room{k}")
        assert plan.points
        frames += _check_clip_limits(plan, spec, mesh)
    assert frames > 12 * 10  # clips, not single frames


def test_planning_is_deterministic_for_a_seed() -> None:
    mesh = scenes.random_furnished_room(np.random.default_rng(7))
    spec = JobSpec.model_validate({"seed": 2, "points": {"count": 3},
                                   "views": {"mode": "trajectory", "trajectory_max_frames": 60}})
    a = plan_to_json(make_plan(scenes.as_space(mesh), spec, space_rng(2, "r"), "r"))
    b = plan_to_json(make_plan(scenes.as_space(mesh.copy()), spec, space_rng(2, "r"), "r"))
    c = plan_to_json(make_plan(scenes.as_space(mesh), spec, space_rng(3, "r"), "r"))
    assert a == b and a != c


def test_short_and_cut_clips_are_reported_and_dropped_points_removed() -> None:
    mesh = scenes.random_furnished_room(np.random.default_rng(41))
    spec = JobSpec.model_validate({
        "seed": 1, "points": {"count": 6},
        "views": {"mode": "trajectory", "trajectory_max_frames": 100, "trajectory_min_frames": 30, "resolution": 64},
    })
    plan = make_plan(scenes.as_space(mesh), spec, space_rng(1, "r"), "r")
    notes = plan.clip_notes
    assert notes and plan.shortfall and "trajectory clips of 6 points" in plan.shortfall
    dropped = [n for n in notes if n["outcome"] == "dropped"]
    assert dropped and len(plan.points) == 6 - len(dropped)
    for n in notes:
        assert n["reasons"]
        if n["outcome"] == "dropped":
            assert n["point_idx"] is None and n["frames"] == 0
        else:
            assert len(plan.views_of(n["point_idx"])) == n["frames"] >= 30
    assert all(len(plan.views_of(p.idx)) >= 30 for p in plan.points)
    assert plan_from_json(plan_to_json(plan)).clip_notes == notes
    _check_clip_limits(plan, spec, mesh)


def test_a_route_through_an_obstacle_is_cut_with_reasons() -> None:
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    route = np.array([[0.8, 2.0, 1.2], [2.5, 2.0, 1.2], [4.0, 2.05, 1.2], [5.5, 2.0, 1.2]])  # through the pillar
    point = np.array([5.9, 3.5, 1.0])  # on the +x wall, seen from both sides of the pillar
    lim = Limits.of(ViewSpec(mode="trajectory", trajectory_spacing_m=0.05), 0.1, 0.001)
    clip = fly_clip(route, point, lim, q, np.zeros(2), 0)
    note = clip.note
    assert note is not None and note.frames == len(clip.frames) < note.planned
    assert {"clearance", "outside"} <= set(note.reasons)
    assert scenes.brute_force_distance(mesh, clip.frames).min() >= 0.1
    assert clip.frames[:, 0].max() < 3.6  # the kept run is the longer stretch before the pillar


def test_fixated_clip_around_a_pillar_stays_in_sight() -> None:
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    cams = np.array([[1.0, 1.0, 1.2], [2.0, 3.0, 1.5], [1.5, 2.0, 1.0], [2.6, 1.0, 1.4], [2.5, 0.6, 1.8],
                     [3.0, 3.4, 1.2], [1.0, 3.2, 1.5], [2.0, 1.8, 1.7]])
    point = np.array([[6.0, 2.0, 1.3]])  # on the +x wall; the pillar hides it from (5, 2)
    normal = np.array([[-1.0, 0.0, 0.0]])
    spec = ViewSpec(mode="trajectory", trajectory_spacing_m=0.05, resolution=256)
    sees = np.flatnonzero(scenes.brute_force_visible(mesh, cams, np.repeat(point, len(cams), axis=0), 0.001))
    assert 0 < len(sees) < len(cams)
    views, notes = trajectory(point, normal, (sees,), cams, spec, None, q, 0.001, 0.1, np.random.default_rng(3))
    assert len(views) > 20
    np.testing.assert_array_equal(views.v, np.arange(len(views)))
    pos = _centres(views.world_to_camera)
    truth = scenes.brute_force_visible(mesh, pos, np.repeat(point, len(pos), axis=0), 0.001)
    assert truth.all() and views.in_sight.all()
    nearest = np.linalg.norm(pos[:, None] - cams[None], axis=2).argmin(axis=1)
    np.testing.assert_array_equal(views.camera_idx, nearest)
    assert np.abs(np.diff(views.roll, 2)).max() < 1e-3  # smooth roll


def test_single_camera_gives_one_frame_and_a_note() -> None:
    q = MeshQueries(scenes.box_room())
    cams = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]])
    views, notes = trajectory(np.array([[6.0, 2.0, 1.0]]), np.array([[-1.0, 0, 0]]), (np.array([1]),), cams,
                              ViewSpec(mode="trajectory"), None, q, 0.001, 0.1, np.random.default_rng(0))
    assert len(views) == 1 and views.camera_idx[0] == 1
    np.testing.assert_allclose(np.linalg.inv(views.world_to_camera[0])[:3, 3], cams[1], atol=1e-12)
    assert len(notes) == 1 and notes[0].reasons == {"route": 1} and notes[0].frames == 1


def test_trajectory_knobs_are_validated() -> None:
    with pytest.raises(ValidationError, match="trajectory_min_frames"):
        ViewSpec(mode="trajectory", trajectory_min_frames=50, trajectory_max_frames=20)
    with pytest.raises(ValidationError, match="trajectory_look"):
        ViewSpec.model_validate({"trajectory_look": "behind"})
    with pytest.raises(ValidationError, match="trajectory_max_turn_deg_per_m"):
        ViewSpec.model_validate({"trajectory_max_turn_deg_per_m": 0})
