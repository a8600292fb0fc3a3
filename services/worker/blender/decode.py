"""Decoding the pass render's EXR channels: sRGB encoding of the Combined pass to 8 bits (the reference formula and
an exact table lookup), and single-pass kernels for the face index, depth and curvature arrays (no bpy here).

sRGB:

The reference (IEC 61966-2-1 piecewise curve in float32, rint) is monotonic in its float32 input, so it is a step
function with 255 steps over [0, 1]. Its output for a float32 x is found from x's bit pattern: positive float32s
are ordered as their bits, so the top 16 bits name a bucket of 65536 consecutive floats, and no bucket holds more
than one step (checked when the tables are built). Per bucket: the output at its first float and the first float
(as bits) where the output goes up by one. Exactly the reference's bytes, without float32 pow (7 ms per 512x512
view on one core -> well under 1 ms; tests/worker/blender/test_srgb.py checks every float32 in [0, 1]).
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

_ONE_BITS = int(np.float32(1.0).view(np.uint32))  # 0x3F800000
_SHIFT = 16
_NEVER = np.uint32(0xFFFFFFFF)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Scene-linear [0, 1] -> 8-bit sRGB (IEC 61966-2-1 piecewise curve), uint8: the reference formula."""
    x = np.clip(linear, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.rint(s * 255.0).astype(np.uint8)


@functools.cache
def tables() -> tuple[np.ndarray, np.ndarray]:
    """(first output, bits of the first float with output + 1 or 0xFFFFFFFF) per bucket of [0, 1]'s floats."""
    levels = np.arange(1, 256)
    lo = np.zeros(256, np.int64)  # per level: bisection over bits for the first float whose output >= level
    hi = np.full(256, _ONE_BITS, np.int64)
    lo, hi = lo[1:], hi[1:]
    while (hi - lo > 1).any():
        mid = (lo + hi) // 2
        up = srgb_encode(mid.astype(np.uint32).view(np.float32)).astype(np.int64) >= levels
        hi, lo = np.where(up, mid, hi), np.where(up, lo, mid)
    steps = hi.astype(np.uint32)  # steps[k - 1]: first bits with output >= k (output(0) = 0)
    if not (srgb_encode(steps.view(np.float32)) == levels).all() or (np.diff(steps.astype(np.int64)) <= 0).any():
        raise AssertionError("the sRGB curve is not a one-level-per-step function of float32 bits")
    buckets = np.arange((_ONE_BITS >> _SHIFT) + 1, dtype=np.uint32)
    first = srgb_encode((buckets << _SHIFT).view(np.float32))
    nxt = np.full(len(buckets), _NEVER, np.uint32)
    owner = steps >> _SHIFT
    if len(np.unique(owner)) != len(owner):
        raise AssertionError("a bucket of float32s holds two sRGB steps")
    inside = (steps & ((1 << _SHIFT) - 1)) != 0  # a step at a bucket's first float is already in `first`
    nxt[owner[inside]] = steps[inside]
    return first, nxt


def srgb_masked(r: np.ndarray, g: np.ndarray, b: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """uint8 H x W x 3: srgb_encode of the float32 H x W channels r, g, b where `hit`, 0 elsewhere."""
    first, nxt = tables()
    r, g, b = (np.asarray(c, dtype=np.float32).view(np.uint32) for c in (r, g, b))
    return _encode(r, g, b, hit, first, nxt)


@njit(cache=True, nogil=True)
def _encode(r: np.ndarray, g: np.ndarray, b: np.ndarray, hit: np.ndarray, first: np.ndarray, nxt: np.ndarray
            ) -> np.ndarray:
    h, w = hit.shape
    out = np.zeros((h, w, 3), np.uint8)
    for y in range(h):
        for x in range(w):
            if not hit[y, x]:
                continue
            for c in range(3):
                v = r[y, x] if c == 0 else g[y, x] if c == 1 else b[y, x]
                if v > 0x7F800000:  # NaN, negative floats (-0.0 too, clipped to 0): the reference gives 0
                    continue
                if v >= _ONE_BITS:  # 1.0 and above, +inf: 255
                    out[y, x, c] = 255
                    continue
                k = v >> _SHIFT
                out[y, x, c] = first[k] + (1 if v >= nxt[k] else 0)
    return out


@njit(cache=True, nogil=True)
def faces_hit(depth: np.ndarray, face1: np.ndarray, miss_depth: float, no_face: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hit, face index (uint32, `no_face` where not hit), depth_z (float32, inf where not hit)) from the Depth pass
    and the face-index-plus-one AOV (float32, exact integers): a pixel is hit where depth < miss_depth and the AOV
    is > 0; the same values as the numpy expressions of render._decode, in one pass."""
    h, w = depth.shape
    hit = np.empty((h, w), np.bool_)
    face = np.empty((h, w), np.uint32)
    z = np.empty((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            f = np.int64(face1[y, x])
            ok = depth[y, x] < miss_depth and f > 0
            hit[y, x] = ok
            face[y, x] = f - 1 if ok else no_face
            z[y, x] = depth[y, x] if ok else np.inf
    return hit, face, z


@njit(cache=True, nogil=True)
def curvature_pair(k1: np.ndarray, k2: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """float32 H x W x 2: (k1, k2) where hit, NaN elsewhere."""
    h, w = hit.shape
    out = np.empty((h, w, 2), np.float32)
    for y in range(h):
        for x in range(w):
            if hit[y, x]:
                out[y, x, 0] = k1[y, x]
                out[y, x, 1] = k2[y, x]
            else:
                out[y, x, 0] = out[y, x, 1] = np.nan
    return out


@njit(cache=True, nogil=True)
def unit_normals_kernel(nx: np.ndarray, ny: np.ndarray, nz: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """render.unit_normals in one pass: the same float32 operations in the same order (IEEE, no fast-math)."""
    h, w = hit.shape
    out = np.zeros((h, w, 3), np.float32)
    tiny = np.float32(1e-12)
    for y in range(h):
        for x in range(w):
            a, b, c = nx[y, x], ny[y, x], nz[y, x]
            norm = np.sqrt(a * a + b * b + c * c)
            if not hit[y, x] or not norm > 0:
                continue
            scale = max(norm, tiny)
            out[y, x, 0] = a / scale
            out[y, x, 1] = b / scale
            out[y, x, 2] = c / scale
    return out
