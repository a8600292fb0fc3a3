"""Derived cues on pass sets made by an independent ray caster (no Blender): encodings and formulas."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from PIL import Image

from services.core.camera import look_at
from services.core.jobspec import CueParams
from services.core.plan import nonfixated as plan_nonfixated
from services.core.plan import point_info
from services.core.plan import vanishing_points as plan_vanishing_points
from services.worker.context import SemanticsUnavailableError, ViewContext
from services.worker.cues.encoding import encode_json
from services.worker.executor import produce
from services.worker.passes import ViewGeometry, ViewPasses
from tests.fixtures.plans import small_plan
from tests.fixtures.raycast import raycast, raycast_passes

RES = 64


def decode_png(data: bytes) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(data)))


def plane_scene(tilt_deg: float = 30.0, dist: float = 3.0) -> tuple[trimesh.Trimesh, ViewGeometry]:
    """A large square in the z = 0 plane, tilted about x, seen from `dist` along +z."""
    plane = trimesh.Trimesh([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    a = np.radians(tilt_deg)
    R = trimesh.transformations.rotation_matrix(a, [1, 0, 0])
    plane.apply_transform(R)
    W = look_at(np.array([0.0, 0.0, dist]), np.zeros(3), up=np.array([0.0, 1.0, 0.0]))
    return plane, ViewGeometry(W, np.radians(60), RES)


def cube_scene() -> tuple[trimesh.Trimesh, ViewGeometry]:
    """A unit cube seen from a corner direction: three faces meet at the image centre."""
    cube = trimesh.creation.box(extents=[1, 1, 1])
    W = look_at(np.array([2.0, -2.0, 2.0]), np.zeros(3))
    return cube, ViewGeometry(W, np.radians(50), 128)


def test_depth_encodings_decode_to_metres() -> None:
    mesh, g = plane_scene()
    ctx = ViewContext(g, passes=raycast_passes(mesh, g))
    cast = raycast(mesh, g)
    z = decode_png(produce("depth_zbuffer", ctx)).astype(np.float64)
    e = decode_png(produce("depth_euclidean", ctx)).astype(np.float64)
    assert np.all(z < 65535)
    np.testing.assert_allclose(z / 512.0, cast.z, atol=1 / 1024 + 1e-6)
    np.testing.assert_allclose(e / 512.0, cast.t, atol=1 / 1024 + 1e-6)
    assert np.all(decode_png(produce("mask_valid", ctx)) == 255)


def test_max_depth_marks_far_surfaces_as_none() -> None:
    mesh, g = plane_scene(tilt_deg=60.0)
    cast = raycast(mesh, g)
    params = CueParams(max_depth_m=4.0)
    ctx = ViewContext(g, params, passes=raycast_passes(mesh, g))
    z = decode_png(produce("depth_zbuffer", ctx))
    far = cast.hit & (cast.z > 4.0)
    near = cast.hit & (cast.z <= 4.0)
    assert far.any() and near.any()
    assert np.all(z[far] == 65535) and np.all(z[near] < 65535)
    mask = decode_png(produce("mask_valid", ctx))
    np.testing.assert_array_equal(mask == 255, near)
    assert np.all(decode_png(produce("depth_euclidean", ctx))[far] == 65535)


def test_normal_decodes_with_omnidata_convention() -> None:
    mesh, g = plane_scene(tilt_deg=30.0)
    ctx = ViewContext(g, passes=raycast_passes(mesh, g))
    px = decode_png(produce("normal", ctx)).astype(np.float64) / 255.0
    n = np.stack([1 - 2 * px[..., 0], 2 * px[..., 1] - 1, 2 * px[..., 2] - 1], axis=-1)
    # The plane turned 30 deg about world x (= camera x): its normal leans towards camera-down (y up axis: -).
    expect = np.array([0.0, -np.sin(np.radians(30)), np.cos(np.radians(30))])
    assert np.max(np.linalg.norm(n - expect, axis=-1)) < 0.01


def test_background_normal_is_128_and_depth_none() -> None:
    mesh, g = cube_scene()
    ctx = ViewContext(g, passes=raycast_passes(mesh, g))
    bg = ~raycast(mesh, g).hit
    assert bg.any()
    assert np.all(decode_png(produce("normal", ctx))[bg] == 128)
    assert np.all(decode_png(produce("depth_zbuffer", ctx))[bg] == 65535)
    assert np.all(decode_png(produce("mask_valid", ctx))[bg] == 0)
    frag = np.load(io.BytesIO(produce("fragments", ctx)))
    assert np.all(frag[bg] == 4294967295)
    np.testing.assert_array_equal(frag[~bg], raycast(mesh, g).tri[~bg])


def test_reshading_is_albedo_times_cosine_to_the_camera() -> None:
    mesh, g = cube_scene()
    cast = raycast(mesh, g)
    ctx = ViewContext(g, CueParams(reshading_albedo=0.9), passes=raycast_passes(mesh, g))
    img = decode_png(produce("reshading", ctx)).astype(np.float64)
    h = cast.hit
    to_cam = g.center - cast.loc
    to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
    fn = mesh.face_normals[np.maximum(cast.tri, 0)]
    cos = np.abs(np.einsum("hwc,hwc->hw", fn, to_cam))
    expect = np.rint(255 * 0.9 * cos)
    assert np.max(np.abs(img[h] - expect[h])) <= 1
    assert np.all(img[~h] == 0)


def test_position_is_world_xyz_with_nan_background() -> None:
    from services.worker.cues.encoding import decode_exr_rgb

    mesh, g = cube_scene()
    cast = raycast(mesh, g)
    pos = decode_exr_rgb(produce("position", ViewContext(g, passes=raycast_passes(mesh, g))))
    assert pos.shape == (128, 128, 3) and pos.dtype == np.float32
    np.testing.assert_allclose(pos[cast.hit], cast.loc[cast.hit], atol=2e-5)
    assert np.all(np.isnan(pos[~cast.hit]))


def test_curvature_encoding() -> None:
    mesh, g = plane_scene()
    p = raycast_passes(mesh, g)
    k = np.zeros((RES, RES, 2), dtype=np.float32)
    k[:, :8] = [100.0, -100.0]  # beyond the +-1/0.03 clip
    k[:, 8:16] = [1 / 0.06, -1 / 0.06]  # half the clip
    p.curvature = k
    img = decode_png(produce("principal_curvature", ViewContext(g, passes=p)))
    assert img.dtype == np.uint8 and img.shape == (RES, RES, 3)
    assert np.all(img[:, :8, :2] == [254, 0])
    assert np.all(img[:, 8:16, :2] == [190, 64])  # round(127 * 1.5), round(127 * 0.5)
    assert np.all(img[:, 16:, :2] == 127) and np.all(img[..., 2] == 0)
    with pytest.raises(RuntimeError, match="curvature"):
        produce("principal_curvature", ViewContext(g, passes=raycast_passes(mesh, g)))


def test_edges_and_keypoints() -> None:
    mesh, g = cube_scene()
    cast = raycast(mesh, g)
    p = raycast_passes(mesh, g)
    # Texture: a bright square in the middle of the image.
    p.rgb[:] = 40
    p.rgb[48:80, 48:80] = 220
    ctx = ViewContext(g, passes=p)
    et = decode_png(produce("edge_texture", ctx)).astype(np.float64)
    assert et[64, 48] > 1000 and et[64, 64] == 0 and et[10, 10] == 0
    eo = decode_png(produce("edge_occlusion", ctx)).astype(np.float64)
    assert np.all(eo[~cast.hit] == 0)
    sil = cast.hit & ~np.pad(cast.hit, 1)[2:, 1:-1]  # bottom silhouette pixels
    assert eo[sil].mean() > 10 * max(eo[32:96, 32:96].mean(), 1.0)
    kp2 = decode_png(produce("keypoints2d", ctx)).astype(np.float64)
    # The square is a blob: the strongest 2D keypoint response lies inside it, around its centre.
    y, x = np.unravel_index(np.argmax(kp2), kp2.shape)
    assert 52 <= y <= 76 and 52 <= x <= 76
    kp3 = decode_png(produce("keypoints3d", ctx)).astype(np.float64)
    assert np.all(kp3[~cast.hit] == 0)
    # The cube's near corner (image centre) is a 3D keypoint; a face centre is not.
    corner = kp3[60:68, 60:68].mean()
    uv_face = np.array([[40, 64], [88, 64], [64, 96]])
    face = min(kp3[v - 3:v + 3, u - 3:u + 3].mean() for u, v in uv_face)
    assert corner > 3 * face and corner > 5000


def test_segmentations_split_colours_and_faces() -> None:
    mesh, g = cube_scene()
    cast = raycast(mesh, g)
    p = raycast_passes(mesh, g)
    p.rgb[cast.hit] = [200, 40, 40]
    p.rgb[:, 64:][cast.hit[:, 64:]] = [40, 40, 200]
    ctx = ViewContext(g, passes=p)
    s2 = decode_png(produce("segment_unsup2d", ctx))
    assert s2.dtype == np.uint16 or s2.dtype == np.int32
    assert np.all(s2[~cast.hit] == 0)
    assert len(np.unique(s2[cast.hit])) == 2
    assert s2[64, 40] != s2[64, 90]
    s25 = decode_png(produce("segment_unsup25d", ctx))
    labels = np.unique(s25[cast.hit])
    assert 3 <= len(labels) <= 8 and 0 not in labels
    # Each of the three visible cube faces is dominated by one segment.
    for f in np.unique(mesh.face_normals[cast.tri[cast.hit]], axis=0):
        pix = cast.hit & np.all(np.isclose(mesh.face_normals[np.maximum(cast.tri, 0)], f), axis=-1)
        _, counts = np.unique(s25[pix], return_counts=True)
        assert counts.max() > 0.8 * pix.sum()


def test_superpixel_count_is_bounded() -> None:
    from services.worker.cues.segmentation import superpixels

    noise = np.random.default_rng(0).random((96, 96, 3)).astype(np.float32)
    labels = superpixels(noise, scale=1.0, sigma=0.0, min_size=1, max_count=40)
    assert labels.max() + 1 <= 40


def test_semantic_cues_need_labels() -> None:
    mesh, g = cube_scene()
    ctx = ViewContext(g, passes=raycast_passes(mesh, g))
    for cue in ("segment_semantic", "segment_instance", "segment_panoptic"):
        with pytest.raises(SemanticsUnavailableError, match="unlabelled"):
            produce(cue, ctx)
    cls = np.arange(len(mesh.faces), dtype=np.int32) // 2 + 1
    inst = np.arange(len(mesh.faces), dtype=np.int32) + 300
    cast = raycast(mesh, g)
    ctx = ViewContext(g, passes=raycast_passes(mesh, g, face_class=cls, face_instance=inst))
    sem = decode_png(produce("segment_semantic", ctx))
    ins = decode_png(produce("segment_instance", ctx)).astype(np.int64)
    np.testing.assert_array_equal(sem[cast.hit], cls[cast.tri[cast.hit]])
    np.testing.assert_array_equal(ins[cast.hit], inst[cast.tri[cast.hit]])
    assert np.all(sem[~cast.hit] == 0) and np.all(ins[~cast.hit] == 0)
    pan = decode_png(produce("segment_panoptic", ctx)).astype(np.int64)
    np.testing.assert_array_equal(pan[..., 0], sem)
    np.testing.assert_array_equal(pan[..., 1] * 256 + pan[..., 2], ins)
    # Negative ids ("unlabelled" in some scans) become 0; ids the encoding cannot hold are refused by name.
    neg = ViewContext(g, passes=raycast_passes(mesh, g, face_class=cls * 0 - 1, face_instance=inst))
    assert np.all(decode_png(produce("segment_semantic", neg)) == 0)
    big = ViewContext(g, passes=raycast_passes(mesh, g, face_class=cls + 300, face_instance=inst))
    with pytest.raises(ValueError, match="class id 30[0-9] in view exceeds 255"):
        produce("segment_semantic", big)


def test_passes_round_trip_gives_identical_cues() -> None:
    mesh, g = cube_scene()
    cls = np.arange(len(mesh.faces), dtype=np.int32)
    p = raycast_passes(mesh, g, face_class=cls, face_instance=cls)
    p.curvature = np.full((128, 128, 2), 3.0, dtype=np.float32)
    a = ViewContext(g, passes=p)
    data = produce("passes", a)
    b = ViewContext(None, passes=ViewPasses.from_bytes(data))
    for cue in ("rgb", "normal", "depth_euclidean", "principal_curvature", "segment_panoptic", "fragments",
                "keypoints3d", "position"):
        assert produce(cue, a) == produce(cue, b), cue


def test_plan_cues_are_the_plan_functions_json() -> None:
    plan = small_plan()
    view = plan.view(1, 0)
    ctx = ViewContext(view, plan=plan)
    info = point_info(plan, view)
    assert produce("point_info", ctx) == encode_json(info)
    assert produce("nonfixated", ctx) == encode_json(plan_nonfixated(plan, 1))
    assert produce("vanishing_points", ctx) == encode_json(plan_vanishing_points(info))
    assert produce("point_info", ViewContext(view, plan=plan)) == produce("point_info", ctx)  # deterministic
    with pytest.raises(RuntimeError, match="plan"):
        produce("nonfixated", ViewContext(view))
    # A ready point_info (from the database) needs no plan.
    assert produce("point_info", ViewContext(view, point_info=info)) == encode_json(info)
