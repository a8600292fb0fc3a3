"""Decoding the pass render's EXR channels: sRGB encoding of the Combined pass to 8 bits (the reference
formula and an exact table lookup), single-pass kernels for the face index, depth and curvature arrays, and
the normals derived from the face index (no bpy here).

sRGB:

The reference (IEC 61966-2-1 piecewise curve in float32, rint) is monotonic in its float32 input, so it is a
step function with 255 steps over [0, 1]. Its output for a float32 x is found from x's bit pattern: positive
float32s are ordered as their bits, so the top 16 bits name a bucket of 65536 consecutive floats, and no
bucket holds more than one step (checked when the tables are built). Per bucket: the output at its first float
and the first float (as bits) where the output goes up by one. Exactly the reference's bytes, without float32
pow (7 ms per 512x512 view on one core -> well under 1 ms; tests/worker/blender/test_srgb.py checks every
float32 in [0, 1]).
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
    if (
        not (srgb_encode(steps.view(np.float32)) == levels).all()
        or (np.diff(steps.astype(np.int64)) <= 0).any()
    ):
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
    """(hit, face index (uint32, `no_face` where not hit), depth_z (float32, inf where not hit)) from the
    Depth pass and the face-index-plus-one AOV (float32, exact integers): a pixel is hit where depth <
    miss_depth and the AOV is > 0; the same values as the numpy expressions of render._decode, in one pass."""
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


def unit_face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """float32 F x 3 unit normals (v1 - v0) x (v2 - v0) of the triangles, in float64 from the float32 vertices
    Blender renders; 0 for a zero-area triangle (whose Normal pass normalises to 0 too)."""
    v = np.asarray(vertices, dtype=np.float32).astype(np.float64)
    f = np.asarray(faces, dtype=np.int64)
    c = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(c, axis=1)
    ok = length > 0
    c[ok] /= length[ok, None]
    c[~ok] = 0.0
    return c.astype(np.float32)


@njit(cache=True, nogil=True)
def facing_normals(
    face: np.ndarray, hit: np.ndarray, face_normals: np.ndarray, rotation: np.ndarray, f: float, cx: float,
    cy: float,
) -> np.ndarray:
    """float32 H x W x 3 world normal of the seen triangle, turned against the pixel's ray where the ray meets
    its back (as Cycles turns a back-facing hit's normal), 0 where nothing is hit.

    What the Normal pass gives for flat-shaded triangles, without rendering it: Cycles' float32 normal of the
    same vertices differs by at most a few 1e-7 (tests/worker/blender/test_pass_identity.py). The side is the
    sign of n . (R^T (u + 0.5 - cx, v + 0.5 - cy, f)), the ray's world direction up to a positive factor.
    """
    h, w = hit.shape
    out = np.zeros((h, w, 3), np.float32)
    for y in range(h):
        ray_y = (y + 0.5 - cy) / f
        for x in range(w):
            if not hit[y, x]:
                continue
            ray_x = (x + 0.5 - cx) / f
            i = face[y, x]
            along = 0.0
            for k in range(3):
                along += np.float64(face_normals[i, k]) * (rotation[0, k] * ray_x + rotation[1, k] * ray_y
                                                           + rotation[2, k])
            for k in range(3):
                out[y, x, k] = -face_normals[i, k] if along > 0 else face_normals[i, k]
    return out
