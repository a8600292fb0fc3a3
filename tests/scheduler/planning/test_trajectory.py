# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Trajectory views: free-space routes, curvature-bounded smoothing, verified frames, limits, notes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from pydantic import ValidationError

from services.core.db.jobs import create_job
from services.core.db.models import Job
from services.core.domain.camera import camera_center, intrinsics, project
from services.core.domain.jobspec import JobSpec, ViewSpec
from services.core.domain.plan import (
    CLIP_NOTES_IN_SUMMARY,
    SpacePlan,
    clip_summary,
    plan_from_json,
    plan_to_json,
)
from services.core.ingest.registry import register_space
from services.core.settings import get_settings
from services.scheduler.loop import Scheduler
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.paths import (
    Limits,
    longest_run,
    resample,
    rotation_angles,
    smooth_path,
    trim,
    turn_angles,
)
from services.scheduler.planning.routes import free_space_graph
from services.scheduler.planning.trajectory import OBJECT_REFERENCE_M, fly_clip, trajectory, verify_clip
from services.scheduler.planning.visibility import MeshQueries
from services.scheduler.transport import NullTransport
from tests.fixtures import scenes
from tests.fixtures.jobs import finish, sqlite_sm  # noqa: F401  (fixtures)


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


def _check_clip_limits(
    plan: SpacePlan, spec: JobSpec, mesh, scale: float = 1.0, clearance: float | None = None
) -> int:
    """Assert every clip of a plan against the spec's limits by independent geometry, lengths (spacing,
    per-metre limits) multiplied by `scale`; frames checked."""
    vs = spec.views
    spacing = vs.trajectory_spacing_m * scale
    clearance = spec.cameras.clearance_m if clearance is None else clearance
    checked = 0
    for point in plan.points:
        views = plan.views_of(point.idx)
        assert 1 <= len(views) <= vs.trajectory_max_frames
        W = np.stack([v.world_to_camera for v in views])
        c = _centres(W)
        if len(c) > 1:
            step = np.linalg.norm(np.diff(c, axis=0), axis=1)
            assert np.abs(step - spacing).max() < 0.01 * spacing
            assert (
                rotation_angles(W).max()
                <= np.radians(vs.trajectory_max_view_deg_per_m) * step.max() / scale + 1e-9
            )
        if len(c) > 2:
            assert (
                turn_angles(c).max()
                <= np.radians(vs.trajectory_max_turn_deg_per_m) * vs.trajectory_spacing_m + 1e-9
            )
        assert scenes.brute_force_distance(mesh, c).min() >= clearance
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
    # long clips (loops for fixated ones), not single frames
    assert frames > 12 * (40 if look == "point" else 25)


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
    spec = JobSpec.model_validate(
        {
            "seed": 1, "points": {"count": 6},
            "views": {
                "mode": "trajectory", "trajectory_max_frames": 100, "trajectory_min_frames": 30,
                "resolution": 64,
            },
        }
    )
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
    # through the pillar
    route = np.array([[0.8, 2.0, 1.2], [2.5, 2.0, 1.2], [4.0, 2.05, 1.2], [5.5, 2.0, 1.2]])
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
    views, notes = trajectory(
        point, normal, (sees,), cams, spec, None, q, 0.001, 0.1, np.random.default_rng(3)
    )
    assert len(views) > 20
    np.testing.assert_array_equal(views.v, np.arange(len(views)))
    pos = _centres(views.world_to_camera)
    truth = scenes.brute_force_visible(mesh, pos, np.repeat(point, len(pos), axis=0), 0.001)
    assert truth.all() and views.in_sight.all()
    nearest = np.linalg.norm(pos[:, None] - cams[None], axis=2).argmin(axis=1)
    np.testing.assert_array_equal(views.camera_idx, nearest)
    assert np.abs(np.diff(views.roll, 2)).max() < 1e-3  # smooth roll


def test_a_single_camera_gives_a_loop_or_arc_not_one_frame_and_a_note() -> None:
    mesh = scenes.box_room()  # 6 x 4 x 2.7 m, empty
    q = MeshQueries(mesh)
    cams = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]])
    point = np.array([6.0, 2.0, 1.0])
    lim = Limits.of(ViewSpec(mode="trajectory"), 0.1, 0.001)
    # no route: the camera alone, one frame, reported
    clip = fly_clip(cams[1:], point, lim, q, np.zeros(2), 0)
    assert len(clip.frames) == 1 and clip.note is not None and clip.note.reasons == {"route": 1}
    np.testing.assert_allclose(clip.frames[0], cams[1])
    # but a loop (round the camera, or an arc round the point) stays in the room, in sight, within the limits
    views, notes = trajectory(point[None], np.array([[-1.0, 0, 0]]), (np.array([1]),), cams,
                              ViewSpec(mode="trajectory"), None, q, 0.001, 0.1, np.random.default_rng(0))
    pos = _centres(views.world_to_camera)
    assert len(views) > 30 and views.in_sight.all()
    ring = np.linalg.norm((pos - point)[:, :2], axis=1)
    assert ring.min() > 2.0  # nearer, moving sideways would turn the view faster than 30 deg/m
    assert scenes.brute_force_distance(mesh, pos).min() >= 0.1
    assert turn_angles(pos).max() <= np.radians(6.0) + 1e-9 and rotation_angles(
        views.world_to_camera
    ).max() <= np.radians(3.0)


def test_trajectory_knobs_are_validated() -> None:
    with pytest.raises(ValidationError, match="trajectory_min_frames"):
        ViewSpec(mode="trajectory", trajectory_min_frames=50, trajectory_max_frames=20)
    with pytest.raises(ValidationError, match="trajectory_look"):
        ViewSpec.model_validate({"trajectory_look": "behind"})
    with pytest.raises(ValidationError, match="trajectory_max_turn_deg_per_m"):
        ViewSpec.model_validate({"trajectory_max_turn_deg_per_m": 0})


def _object(rng: np.random.Generator) -> trimesh.Trimesh:
    """A closed object about 0.3 m across: an ellipsoid with a post through it (a concave joint)."""
    body = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    body.apply_scale(rng.uniform([1.0, 0.8, 0.6], [1.6, 1.2, 1.0]))
    post = trimesh.creation.box(extents=[0.04, 0.04, 0.3])
    return trimesh.util.concatenate([body, post])


@pytest.mark.parametrize("look", ["point", "ahead"])
def test_object_mode_clips_orbit_the_point_with_lengths_scaled_to_the_sphere(look: str) -> None:
    mesh = _object(np.random.default_rng(4))
    spec = JobSpec.model_validate({
        "seed": 4, "cameras": {"mode": "object"}, "points": {"count": 4},
        "views": {"mode": "trajectory", "trajectory_look": look, "resolution": 64},
    })
    plan = make_plan(scenes.as_space(mesh), spec, space_rng(4, "obj"), "obj")
    radius = spec.cameras.object_distance_factor * float(mesh.bounding_sphere.primitive.radius)
    scale = radius / OBJECT_REFERENCE_M  # a 0.1 m spacing on a 5 m sphere: the same per-frame figures
    cams = np.stack([c.position for c in plan.cameras])
    own = float(scenes.brute_force_distance(mesh, cams).min())  # object cameras may sit nearer than 0.1 m
    frames = _check_clip_limits(plan, spec, mesh, scale, clearance=min(spec.cameras.clearance_m, own / 2))
    assert len(plan.points) == 4 and frames >= 4 * 150  # videos, not the single frames of fixed limits
    for point in plan.points:  # an orbit: the camera keeps its distance to the point
        c = _centres(np.stack([v.world_to_camera for v in plan.views_of(point.idx)]))
        np.testing.assert_allclose(np.linalg.norm(c - point.position, axis=1), radius, rtol=0.02)


def test_a_clip_cut_between_two_frames_reports_why() -> None:
    wall = trimesh.Trimesh(vertices=[[1.05, -1, -1], [1.05, 1, -1], [1.05, 1, 1], [1.05, -1, 1]],
                           faces=[[0, 1, 2], [0, 2, 3]])  # a thin wall between frames 10 and 11
    line = np.stack([np.linspace(0.0, 2.0, 21), np.zeros(21), np.zeros(21)], axis=1)
    lim = Limits.of(ViewSpec(mode="trajectory", trajectory_look="ahead"), 0.0, 0.001)
    clip = verify_clip(line, line, np.array([5.0, 0.0, 0.0]), lim, MeshQueries(wall), np.zeros(2), 0)
    assert clip.note is not None and len(clip.frames) == clip.note.frames == 11
    assert clip.note.reasons == {"outside": 1}


def test_frames_near_a_wall_are_pushed_out_not_cut() -> None:
    mesh = scenes.pillar_room()  # pillar x 3.7..4.3, y 1.7..2.3
    q = MeshQueries(mesh)
    # 7 cm from the pillar
    line = np.stack([np.linspace(1.0, 5.5, 91), np.full(91, 1.63), np.full(91, 1.2)], axis=1)
    lim = Limits.of(ViewSpec(mode="trajectory"), 0.1, 0.001)
    point = np.array([5.95, 1.63, 1.2])  # on the +x wall, ahead: the view hardly turns
    clip = verify_clip(line, line, point, lim, q, np.zeros(2), 0)
    assert clip.note is None and len(clip.frames) >= 44  # nothing cut (the path got a little longer)
    dist = scenes.brute_force_distance(mesh, clip.frames)
    assert dist.min() >= 0.1 and scenes.brute_force_distance(mesh, line).min() < 0.08
    assert turn_angles(clip.frames).max() <= lim.turn_rate * lim.spacing + 1e-9
    step = np.linalg.norm(np.diff(clip.frames, axis=0), axis=1)
    assert np.abs(step - 0.1).max() < 1e-3
    far = np.abs(clip.frames[:, 0] - 4.0) > 3.0  # far from the pillar the path stays put
    np.testing.assert_allclose(clip.frames[far, 1], 1.63, atol=1e-3)


def test_closest_within_matches_brute_force() -> None:
    mesh = scenes.pillar_room()
    q = MeshQueries(mesh)
    pts = np.random.default_rng(1).uniform([0.05, 0.05, 0.05], [5.95, 3.95, 2.65], (200, 3))
    dist, closest = q.closest_within(pts, 0.3)
    truth = scenes.brute_force_distance(mesh, pts)
    near = truth < 0.3
    np.testing.assert_allclose(dist[near], truth[near], atol=1e-9)
    assert np.isinf(dist[~near]).all()
    np.testing.assert_allclose(np.linalg.norm(closest[near] - pts[near], axis=1), truth[near], atol=1e-9)


def test_scheduler_plans_a_trajectory_job_and_reports_its_clips(
    sqlite_sm, local_store, scenes_dir, tmp_path
) -> None:
    spec = JobSpec.model_validate({
        "cues": ["point_info"], "cameras": {"mode": "object", "object_count": 16}, "points": {"count": 2},
        "views": {"mode": "trajectory", "trajectory_max_frames": 24, "trajectory_min_frames": 20,
                  "trajectory_max_view_deg_per_m": 20, "resolution": 64},
    })
    with sqlite_sm() as s:
        space = register_space(s, local_store, owner="alice", name="bunny",
                               source_path=scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply")
        job_id = create_job(s, owner="alice", spec=spec, spaces=[space]).id
        s.commit()
    tr = NullTransport()
    sched = Scheduler(
        sqlite_sm, local_store, tr, get_settings(data_dir=tmp_path, dispatch_window=100), "sched-1"
    )
    assert sched.tick().planned == [job_id]
    plan = plan_from_json(local_store.get_bytes(f"jobs/{job_id}/_plan/bunny.json"))
    with sqlite_sm() as s:
        job = s.get(Job, job_id)
        planned = job.plan_summary["spaces"]["bunny"]
        assert planned["clips"] == clip_summary(plan.clip_notes, CLIP_NOTES_IN_SUMMARY)
        assert planned["views"] == len(plan.views) == sum(len(plan.views_of(p.idx)) for p in plan.points)
        assert all(len(plan.views_of(p.idx)) >= 20 for p in plan.points)  # videos
        assert planned["shortfall"] == plan.shortfall
        for _ in range(5):
            finish(s, job, [i for i, _ in tr.sent])
            tr.sent.clear()
            res = sched.tick()
            if res.finished:
                break
        assert [(f.job_id, f.state) for f in res.finished] == [(job_id, "done")]
    doc = json.loads(local_store.get_bytes(f"jobs/{job_id}/job.json"))
    assert doc["spaces"]["bunny"]["clips"] == planned["clips"]
    lines = local_store.get_bytes(f"jobs/{job_id}/manifest.jsonl").decode().splitlines()
    assert len(lines) == len(plan.views)
