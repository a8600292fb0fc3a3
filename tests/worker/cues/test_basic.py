"""Basic cues (services/worker/cues/basic.py) on ray-cast pass sets (no Blender): encodings and formulas."""

from __future__ import annotations

import io

import numpy as np
import pytest

from services.core.domain.jobspec import CueParams
from services.worker.context import ViewContext
from services.worker.executor import produce
from tests.fixtures.raycast import cube_scene, decode_png, plane_scene, raycast, raycast_passes

RES = 64


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
    # the job's position_compression reaches the file: ZIP, same floats bit for bit
    zipped = produce("position", ViewContext(g, CueParams(position_compression="zip"),
                                             passes=raycast_passes(mesh, g)))
    assert zipped[:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic
    assert np.array_equal(decode_exr_rgb(zipped).view(np.uint32), pos.view(np.uint32))
    assert len(zipped) < pos.nbytes  # an uncompressed file is at least the floats


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
