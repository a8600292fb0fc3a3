"""make_plan end to end (pure), determinism, JSON, and the plan-stage cues built from a plan."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import trimesh

from services.core.domain.camera import (
    CONVENTIONS,
    blender_matrix_world,
    camera_center,
    intrinsics,
    look_at,
    pixel_rays,
    project,
    quaternion_wxyz_to_rotation,
)
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import (
    CameraPose,
    PlannedView,
    PointOfInterest,
    SpacePlan,
    plan_from_json,
    plan_to_json,
)
from services.core.domain.plan_cues import nonfixated, point_info, vanishing_points
from services.core.ingest.loading import LoadedSpace, load_space
from services.scheduler.planning import make_plan, plan_chunks, space_rng
from tests.fixtures import scenes
from tests.fixtures.vector_isa import vector_isa

OMNIDATA_KEYS = {
    "point_uuid", "view_id", "camera_uuid", "camera_location", "camera_rotation_final",
    "camera_rotation_final_quaternion", "field_of_view_rads", "resolution", "point_location", "point_normal",
    "obliqueness_angle", "camera_distance", "nonfixated_points_in_view",
}

SMALL = {
    "cameras": {"max_count": 30, "min_spacing_m": 0.8},
    "points": {"count": 25, "min_views": 3, "max_views": 4},
    "views": {"resolution": 320},
}


@pytest.fixture(scope="module")
def room_plan() -> SpacePlan:
    spec = JobSpec.model_validate(SMALL)
    return make_plan(scenes.as_space(scenes.l_room()), spec, space_rng(spec.seed, "lroom"), "lroom")


def _euler_xyz_to_matrix(e: list[float]) -> np.ndarray:
    x, y, z = e
    Rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def test_plan_shape(room_plan: SpacePlan) -> None:
    p = room_plan
    assert len(p.points) == 25 and p.shortfall is None
    assert all(c.source == "generated" for c in p.cameras)
    assert [c.idx for c in p.cameras] == list(range(len(p.cameras)))
    assert len({c.uuid for c in p.cameras} | {q.uuid for q in p.points}) == len(p.cameras) + len(p.points)
    keys = [(v.point_idx, v.v) for v in p.views]
    assert keys == sorted(keys)
    for q in p.points:
        vs = p.views_of(q.idx)
        assert 3 <= len(vs) <= 4 and [v.v for v in vs] == list(range(len(vs)))
        assert {v.camera_idx for v in vs} <= set(q.camera_idxs)
        assert all(v.in_sight and v.resolution == 320 for v in vs)


def test_same_seed_same_bytes_other_seed_differs() -> None:
    space = scenes.as_space(scenes.pillar_room())
    spec = JobSpec.model_validate(SMALL)
    a = plan_to_json(make_plan(space, spec, space_rng(7, "room"), "room"))
    b = plan_to_json(make_plan(scenes.as_space(scenes.pillar_room()), spec, space_rng(7, "room"), "room"))
    c = plan_to_json(make_plan(space, spec, space_rng(8, "room"), "room"))
    assert a == b
    assert a != c
    traj = JobSpec.model_validate({**SMALL, "views": {"mode": "trajectory", "trajectory_spacing_m": 0.3}})
    t1 = plan_to_json(make_plan(space, traj, space_rng(7, "room"), "room"))
    t2 = plan_to_json(make_plan(space, traj, space_rng(7, "room"), "room"))
    assert t1 == t2 and t1 != a


# sha256 of plan_to_json, recorded when the chunked planner became the only one of its specs: a seed must keep
# giving the plan it gave (the chunked specs, one (generated cameras) and the whole ones (nonfixated
# pruning)), on a machine of each vector instruction set (an AMD Zen 4 with AVX-512, a Zen 3 without)
PINNED = {
    "lroom_small": ({"avx512": "77300fbbca3e0a9d99dc2893077385d67f483df89030774f253545c61ab183aa",
                     "avx2": "f439dbc23bbca769ffb70a44e3ca1f5cd676fa6fc4653477e0859902daf3b693"}, SMALL),
    "pillar_prune": ({"avx512": "8301b235ebd7cae476d67c01ab5e2669d8a1dc5af360e56b10710783f050b56c",
                      "avx2": "32ec84c887360acc99f3e4e6a37042dffde56f2b8e6f3adbab6afc0068eaa6ba"},
                     {**SMALL, "views": {"nonfixated_pruning": True}}),
}


@pytest.mark.parametrize("name", sorted(PINNED))
@pytest.mark.parametrize("chunk_views", [None, 7])
def test_plans_keep_their_recorded_bytes_whole_or_in_chunks(name: str, chunk_views: int | None) -> None:
    digests, raw = PINNED[name]
    spec = JobSpec.model_validate(raw)
    space = scenes.as_space(scenes.l_room() if name == "lroom_small" else scenes.pillar_room())
    if chunk_views is None:
        plan = make_plan(space, spec, space_rng(spec.seed, name), name)
    else:
        chunks = plan_chunks(space, spec, space_rng(spec.seed, name), name, chunk_views)
        plan = chunks.collect()
        assert len(plan.views) > 4 * chunk_views and chunks.views == len(plan.views)  # several chunks
    assert hashlib.sha256(plan_to_json(plan).encode()).hexdigest() == digests[vector_isa()]


def test_space_rng_depends_on_seed_and_name_only() -> None:
    assert space_rng(1, "a").random() == space_rng(1, "a").random()
    assert space_rng(1, "a").random() != space_rng(1, "b").random()
    assert space_rng(1, "a").random() != space_rng(2, "a").random()


def test_json_round_trip_is_exact(room_plan: SpacePlan) -> None:
    text = plan_to_json(room_plan)
    back = plan_from_json(text)
    assert plan_to_json(back) == text
    for v, w in zip(room_plan.views, back.views, strict=True):
        np.testing.assert_array_equal(v.world_to_camera, w.world_to_camera)
        assert v.fov == w.fov and v.roll == w.roll
    with pytest.raises(ValueError, match="not a plan"):
        plan_from_json(json.dumps({"format": "other"}))


def test_point_info_keys_and_camera_consistency(room_plan: SpacePlan) -> None:
    for view in room_plan.views[::3]:
        info = point_info(room_plan, view)
        assert OMNIDATA_KEYS <= set(info)
        assert {"K", "world_to_camera", "conventions"} <= set(info)
        assert info["conventions"] == CONVENTIONS
        json.dumps(info, allow_nan=False)  # plain JSON
        K = np.array(info["K"])
        W = np.array(info["world_to_camera"])
        np.testing.assert_allclose(K, intrinsics(info["field_of_view_rads"], info["resolution"]))
        np.testing.assert_allclose(K[0, 0], 160 / np.tan(view.fov / 2))
        uv, z = project(np.array([info["point_location"]]), K, W)
        assert np.abs(uv[0] - [160.0, 160.0]).max() < 1e-6  # fixated: the point is at the image centre
        assert z[0] == pytest.approx(info["camera_distance"])  # ... on the optical axis
        centre = np.array(info["camera_location"])
        np.testing.assert_allclose(centre, camera_center(W), atol=1e-12)
        np.testing.assert_allclose(centre, room_plan.cameras[view.camera_idx].position, atol=1e-12)
        assert info["camera_distance"] == pytest.approx(np.linalg.norm(centre - info["point_location"]))
        # Blender camera rotation: Euler XYZ and wxyz quaternion of matrix_world's rotation
        R_bl = blender_matrix_world(W)[:3, :3]
        np.testing.assert_allclose(_euler_xyz_to_matrix(info["camera_rotation_final"]), R_bl, atol=1e-12)
        np.testing.assert_allclose(
            quaternion_wxyz_to_rotation(info["camera_rotation_final_quaternion"]), R_bl, atol=1e-12
        )
        n = np.array(info["point_normal"])
        d = (centre - info["point_location"]) / info["camera_distance"]
        assert info["obliqueness_angle"] == pytest.approx(np.arccos(n @ d))
        assert info["point_uuid"] == room_plan.points[view.point_idx].uuid
        assert info["view_id"] == view.v


def test_nonfixated_lists_visible_points_at_their_pixels(room_plan: SpacePlan) -> None:
    mesh = scenes.l_room()
    tol = max(0.001, 1e-5 * mesh.scale)
    positions = np.array([q.position for q in room_plan.points])
    total = 0
    for q in room_plan.points[:10]:
        doc = nonfixated(room_plan, q.idx)
        assert doc["point_uuid"] == q.uuid and len(doc["views"]) == len(room_plan.views_of(q.idx))
        for vd, view in zip(doc["views"], room_plan.views_of(q.idx), strict=True):
            listed = [e["point_idx"] for e in vd["points"]]
            assert listed == point_info(room_plan, view)["nonfixated_points_in_view"]
            # independent recomputation: brute-force line of sight from the camera, inside the image
            cam = view.position
            uv, z = project(positions, view.K, view.world_to_camera)
            los = scenes.brute_force_visible(mesh, np.tile(cam, (len(positions), 1)), positions, tol)
            inside = (z > 0) & (uv >= 0).all(axis=1) & (uv < 320).all(axis=1)
            expect = [int(i) for i in np.flatnonzero(los & inside) if i != q.idx]
            assert listed == expect
            for e in vd["points"]:
                np.testing.assert_allclose(e["pixel"], uv[e["point_idx"]], atol=1e-9)
                assert e["depth_zbuffer_m"] == pytest.approx(z[e["point_idx"]])
            total += len(listed)
    assert total > 0


def test_vanishing_points_of_known_cameras() -> None:
    # looking along +X, level: X vanishes at the image centre, Y and Z are parallel to the image
    W = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    info = {"K": intrinsics(np.pi / 2, 100).tolist(), "world_to_camera": W.tolist()}
    vp = vanishing_points(info)
    np.testing.assert_allclose(vp["x"]["image"], [50, 50], atol=1e-9)
    assert vp["y"]["image"] is None and vp["z"]["image"] is None
    np.testing.assert_allclose(vp["x"]["gaussian_sphere"], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(vp["z"]["direction"], [0, -1, 0], atol=1e-12)  # world up is image up
    # pitched down 45 degrees toward +X: Z vanishes straight below the centre at f * tan(45) = f
    W = look_at(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    info = {"K": intrinsics(np.pi / 2, 100).tolist(), "world_to_camera": W.tolist()}
    vp = vanishing_points(info)
    np.testing.assert_allclose(vp["z"]["image"], [50, 50 + 50], atol=1e-9)  # f = 50 px
    np.testing.assert_allclose(vp["x"]["image"], [50, 50 - 50], atol=1e-9)
    for k in "xyz":
        g = np.array(vp[k]["gaussian_sphere"])
        assert np.linalg.norm(g) == pytest.approx(1.0) and g[2] >= 0
        if vp[k]["image"] is not None:  # the image point is the central projection of the sphere point
            K = np.array(info["K"])
            np.testing.assert_allclose((K @ g)[:2] / (K @ g)[2], vp[k]["image"], atol=1e-9)


def test_provided_poses_keep_their_positions_and_uuids() -> None:
    poses = [
        {"location": (1.0, 1.0, 1.2), "uuid": "cam-a"},
        {"location": (4.5, 1.0, 1.5)},
        {"location": (1.5, 3.0, 1.0), "uuid": "cam-c"},
        {"location": (5.0, 3.2, 1.7)},
    ]
    spec = JobSpec.model_validate({"cameras": {"mode": "provided", "poses": poses}, "points": {"count": 10}})
    plan = make_plan(scenes.as_space(scenes.pillar_room()), spec, np.random.default_rng(0), "room")
    np.testing.assert_array_equal([c.position for c in plan.cameras], [p["location"] for p in poses])
    assert [c.source for c in plan.cameras] == ["provided"] * 4
    assert plan.cameras[0].uuid == "cam-a" and plan.cameras[2].uuid == "cam-c"
    assert plan.cameras[1].uuid not in {"cam-a", "cam-c"}
    assert len(plan.points) == 10


def test_bunny_object_mode_plan(shared_scenes) -> None:
    space = load_space(shared_scenes / "stanford_bunny" / "bun_zipper_res2.ply")
    spec = JobSpec.model_validate({
        "cameras": {"mode": "object", "object_count": 24, "object_distance_factor": 2.0},
        "points": {"count": 20, "min_views": 3, "max_views": 3},
    })
    plan = make_plan(space, spec, space_rng(0, "bunny"), "bunny")
    sphere = space.mesh.bounding_sphere.primitive
    d = np.array([np.linalg.norm(c.position - sphere.center) for c in plan.cameras])
    np.testing.assert_allclose(d, 2.0 * sphere.radius, rtol=1e-12)
    assert len(plan.points) == 20 and len(plan.views) == 60 and plan.shortfall is None
    for v in plan.views:
        uv, _ = project(plan.points[v.point_idx].position[None], v.K, v.world_to_camera)
        assert np.abs(uv - 256).max() < 1e-6


def test_banana_textured_object_plan(shared_scenes) -> None:
    space = load_space(shared_scenes / "ycb_banana")
    assert space.has_texture
    spec = JobSpec.model_validate({"cameras": {"mode": "object", "object_count": 16}, "points": {"count": 8}})
    plan = make_plan(space, spec, space_rng(0, "banana"), "banana")
    assert len(plan.points) == 8 and all(len(plan.views_of(p.idx)) >= 3 for p in plan.points)


def test_dataclasses_are_frozen_values() -> None:
    cam = CameraPose(0, [1, 2, 3], "generated", "u")
    with pytest.raises(ValueError):
        cam.position[0] = 5.0  # read-only array
    with pytest.raises(ValueError, match="camera source"):
        CameraPose(0, [1, 2, 3], "guessed", "u")
    p = PointOfInterest(0, [0, 0, 0], [0, 0, 1], "p", np.array([2, 1]))
    assert p.camera_idxs == (2, 1)
    with pytest.raises(ValueError, match="shape"):
        PlannedView(0, 0, 0, np.eye(3), 1.0, 0.0, 64, 0.0, True)


def _probe_fraction(mesh, view, size: int) -> float:
    """Independent share of pixels with a surface: trimesh's own ray caster through the K/world_to_camera
    pixels."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    origins, dirs = pixel_rays(intrinsics(view.fov, size), view.world_to_camera, size, size)
    return float(RayMeshIntersector(mesh).intersects_any(origins, dirs).mean())


def _room_with_holes() -> LoadedSpace:
    """A room without ceiling and with a missing wall: views facing the holes see little surface."""
    room = scenes.box_room(size=(6.0, 4.0, 2.7))
    room.update_faces((room.face_normals[:, 2] > -0.9) & ~(room.face_normals[:, 0] < -0.9))
    return scenes.as_space(trimesh.util.concatenate([room, scenes.table()]))


def test_min_valid_fraction_drops_views_into_holes() -> None:
    from services.scheduler.planning.views import VALID_PROBE_PX

    space = _room_with_holes()
    base = {"cameras": {"max_count": 20, "min_spacing_m": 0.8}, "points": {"count": 20, "min_views": 1},
            "views": {"resolution": 64, "fov_mean_deg": 90, "fov_std_deg": 0}}
    all_views = make_plan(space, JobSpec.model_validate(base), np.random.default_rng(1), "holes")
    fractions = np.array([_probe_fraction(space.mesh, v, VALID_PROBE_PX) for v in all_views.views])
    summary = all_views.valid_fraction
    assert summary["views"] == len(all_views.views) and summary["dropped"] == 0 and summary["threshold"] == 0
    assert summary["median"] == pytest.approx(float(np.median(fractions)), abs=1 / VALID_PROBE_PX**2)
    assert summary["min"] < 0.9 < summary["max"]  # some views look into the holes
    strict = JobSpec.model_validate({**base, "views": {**base["views"], "min_valid_fraction": 0.9}})
    kept = make_plan(space, strict, np.random.default_rng(1), "holes")
    assert kept.valid_fraction["dropped"] == int((fractions < 0.9).sum()) > 0
    assert len(kept.views) <= len(all_views.views) - kept.valid_fraction["dropped"]
    assert all(_probe_fraction(space.mesh, v, VALID_PROBE_PX) >= 0.9 for v in kept.views)
    assert "min_valid_fraction" in (kept.shortfall or "")


def test_min_valid_fraction_cuts_trajectory_clips_without_gaps() -> None:
    space = _room_with_holes()
    spec = JobSpec.model_validate({
        "points": {"count": 4, "min_views": 1},
        "views": {"mode": "trajectory", "resolution": 64, "fov_mean_deg": 90, "fov_std_deg": 0,
                  "trajectory_max_frames": 60, "trajectory_min_frames": 5, "min_valid_fraction": 0.8},
    })
    plan = make_plan(space, spec, np.random.default_rng(1), "holes")
    assert plan.valid_fraction["dropped"] > 0 and plan.points
    _assert_clips_without_gaps(plan, min_frames=5)


def test_nonfixated_pruning_cuts_trajectory_clips_without_gaps() -> None:
    spec = JobSpec.model_validate({"seed": 1, "points": {"count": 5, "min_views": 1}, "views": {
        "mode": "trajectory", "resolution": 64, "trajectory_max_frames": 60, "nonfixated_pruning": True}})
    plan = make_plan(scenes.as_space(scenes.furnished_room()), spec, space_rng(1, "r"), "r")
    assert "nonfixated pruning" in (plan.shortfall or "") and plan.points
    _assert_clips_without_gaps(plan, min_frames=1)


def _assert_clips_without_gaps(plan: SpacePlan, min_frames: int) -> None:
    # every clip is one run of frames at the spec's spacing: no frame cut from inside
    for point in plan.points:
        centres = np.stack([camera_center(v.world_to_camera) for v in plan.views_of(point.idx)])
        assert len(centres) >= min_frames
        np.testing.assert_allclose(np.linalg.norm(np.diff(centres, axis=0), axis=1), 0.1, atol=0.01)
