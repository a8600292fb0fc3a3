"""The pass decode's kernels give the bytes of the numpy expressions they replace, and the normals derived
from the face index are the triangles' normals turned against each pixel's ray
(services.worker.blender.decode)."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.domain.camera import look_at
from services.worker.blender.decode import facing_normals, srgb_encode, srgb_masked, tables, unit_face_normals
from services.worker.passes import ViewGeometry

ONE = int(np.float32(1.0).view(np.uint32))


def reference(rgba: np.ndarray, hit: np.ndarray) -> np.ndarray:
    return np.where(hit[..., None], srgb_encode(rgba[..., :3]), 0).astype(np.uint8)


def check_bits(bits: np.ndarray) -> None:
    f = bits.astype(np.uint32).view(np.float32)
    rgba = np.stack([f, f[::-1], f, f], axis=-1)[None]
    hit = np.ones((1, len(f)), bool)
    assert np.array_equal(srgb_masked(*rgba[..., :3].transpose(2, 0, 1), hit), reference(rgba, hit))


def test_srgb_table_is_exact_around_every_step_and_at_the_ends():
    first, nxt = tables()
    steps = nxt[nxt != 0xFFFFFFFF].astype(np.int64)
    assert len(steps) + len(np.unique(first)) >= 255  # every level is reached
    near = (steps[:, None] + np.arange(-3000, 3000)[None, :]).ravel()
    ends = np.concatenate([np.arange(0, 5000), np.arange(ONE - 5000, ONE + 5000)])
    check_bits(np.clip(np.concatenate([near, ends, np.arange(0, ONE, 997)]), 0, None))
    special = np.array([0.0, -0.0, -1.0, 1.0, 2.0, np.inf, -np.inf, 0.0031308, 0.5], np.float32)
    check_bits(special.view(np.uint32))


def test_srgb_masked_is_zero_where_nothing_is_hit():
    rng = np.random.default_rng(1)
    rgba = rng.random((64, 48, 4), dtype=np.float32) * np.float32(1.2) - np.float32(0.1)
    hit = rng.random((64, 48)) > 0.3
    got = srgb_masked(rgba[..., 0], rgba[..., 1], rgba[..., 2], hit)
    assert np.array_equal(got, reference(rgba, hit)) and (got[~hit] == 0).all() and got[hit].any()


@pytest.mark.slow
def test_srgb_table_is_exact_for_every_float32_in_0_1():
    for start in range(0, ONE + 1, 1 << 24):
        f = np.arange(start, min(start + (1 << 24), ONE + 1), dtype=np.uint32).view(np.float32)
        got = srgb_masked(f[None], f[None], f[None], np.ones((1, len(f)), bool))
        assert np.array_equal(got[0, :, 1], srgb_encode(f)), start


def test_unit_face_normals_are_the_triangles_normals_and_zero_for_zero_area():
    rng = np.random.default_rng(7)
    v = (rng.random((300, 3)) * 4 - 2).astype(np.float32)
    f = np.array([rng.choice(300, 3, replace=False) for _ in range(500)])
    f[:5, 2] = f[:5, 1]  # two corners the same: no area
    n = unit_face_normals(v, f)
    assert n.dtype == np.float32 and n.shape == (500, 3)
    assert (n[:5] == 0).all()
    e1, e2 = v[f[5:, 1]].astype(float) - v[f[5:, 0]], v[f[5:, 2]].astype(float) - v[f[5:, 0]]
    assert np.allclose(np.linalg.norm(n[5:], axis=1), 1.0, atol=1e-6)
    assert np.allclose((n[5:] * e1).sum(1), 0, atol=1e-5) and np.allclose((n[5:] * e2).sum(1), 0, atol=1e-5)
    # (v1 - v0) x (v2 - v0), not its opposite
    assert (np.einsum("ij,ij->i", np.cross(e1, e2), n[5:]) > 0).all()


def test_facing_normals_turn_each_triangle_normal_against_the_pixel_ray():
    rng = np.random.default_rng(11)
    g = ViewGeometry(look_at(np.array([0.3, -2.0, 1.2]), np.array([0.1, 0.4, 0.9])), np.radians(70.0), 48)
    face_normals = rng.normal(size=(40, 3))
    face_normals = (face_normals / np.linalg.norm(face_normals, axis=1, keepdims=True)).astype(np.float32)
    face_normals[3] = 0.0  # a zero-area triangle
    face = rng.integers(0, 40, (48, 48)).astype(np.uint32)
    hit = rng.random((48, 48)) > 0.25
    K = g.K
    got = facing_normals(face, hit, face_normals, g.rotation, K[0, 0], K[0, 2], K[1, 2])
    # Independently: the pixel-centre rays of the camera (ViewGeometry.rays_world), each normal against its
    # ray.
    _, d = g.rays_world()
    n = face_normals[face.ravel()]
    want = np.where(((n * d).sum(1) > 0)[:, None], -n, n).reshape(48, 48, 3)
    want[~hit] = 0.0
    assert got.dtype == np.float32 and np.array_equal(got, want)
    assert ((got[hit] * d.reshape(48, 48, 3)[hit]).sum(-1) <= 0).all()  # every seen normal faces the camera
    assert (np.linalg.norm(got[hit & (face != 3)], axis=-1) > 0.99).all() and (got[face == 3] == 0).all()
