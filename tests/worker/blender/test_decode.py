"""The pass decode's kernels give the bytes of the numpy expressions they replace (services.worker.blender.decode)."""

from __future__ import annotations

import numpy as np
import pytest

from services.worker.blender.decode import srgb_encode, srgb_masked, tables, unit_normals_kernel

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


def test_unit_normals_kernel_is_bit_identical_to_unit_normals():
    from services.worker.blender.render import unit_normals

    rng = np.random.default_rng(7)
    for scale in (1e-3, 1.0, 1e3):
        x, y, z = ((rng.random((64, 64), dtype=np.float32) - 0.5) * np.float32(scale) for _ in range(3))
        x[:4], y[:4], z[:4] = 0, 0, 0
        hit = rng.random((64, 64)) > 0.2
        want = unit_normals(x, y, z, hit)
        got = unit_normals_kernel(x, y, z, hit)
        assert got.dtype == np.float32 and np.array_equal(got.view(np.uint32), want.view(np.uint32))
