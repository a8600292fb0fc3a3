"""Compiled per-pixel passes of keypoints3d's NARF-like interest (keypoints.narf_interest), each the numpy
expressions it replaces bit for bit: the same float32 operations in the same order (numpy's float32 arithmetic
with Python scalars stays float32; its norm and einsum over 3 channels add left to right), without the full-size
temporaries (tests/worker/cues/test_kernels.py against tests/fixtures/reference_narf.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _range(v: np.ndarray, z: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Euclidean range (inf off v) and camera-space points d * range (d * 0 off v: signed zeros as numpy's)."""
    h, w = v.shape
    rng = np.empty((h, w), np.float32)
    P = np.empty((h, w, 3), np.float32)
    for y in range(h):
        for x in range(w):
            r = z[y, x] / d[y, x, 2] if v[y, x] else np.float32(0.0)
            rng[y, x] = r if v[y, x] else np.float32(np.inf)
            for c in range(3):
                P[y, x, c] = d[y, x, c] * r
    return rng, P


@njit(cache=True, nogil=True)
def _borders(v: np.ndarray, rng: np.ndarray, f: np.float32, footprints: np.float32) -> np.ndarray:
    """Foreground borders: a 4-neighbour (inf outside the image) farther by more than footprints * range / f."""
    h, w = v.shape
    border = np.zeros((h, w), np.bool_)
    for y in range(h):
        for x in range(w):
            if not v[y, x]:
                continue
            r = rng[y, x]
            thresh = (footprints * r) / f
            for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                yy, xx = y + dy, x + dx
                rq = rng[yy, xx] if 0 <= yy < h and 0 <= xx < w else np.float32(np.inf)
                if rq - r > thresh:
                    border[y, x] = True
    return border


@njit(cache=True, nogil=True)
def _differences(P: np.ndarray, y: int, x: int) -> tuple:
    """du, dv = P[i + 1] - P[i - 1] along x and y at (y, x), zeros outside (keypoints' central difference)."""
    h, w = P.shape[:2]
    if x == 0:
        du0, du1, du2 = P[y, 1, 0], P[y, 1, 1], P[y, 1, 2]
    elif x == w - 1:
        du0, du1, du2 = -P[y, x - 1, 0], -P[y, x - 1, 1], -P[y, x - 1, 2]
    else:
        du0, du1, du2 = P[y, x + 1, 0] - P[y, x - 1, 0], P[y, x + 1, 1] - P[y, x - 1, 1], P[y, x + 1, 2] - P[y, x - 1, 2]
    if y == 0:
        dv0, dv1, dv2 = P[1, x, 0], P[1, x, 1], P[1, x, 2]
    elif y == h - 1:
        dv0, dv1, dv2 = -P[y - 1, x, 0], -P[y - 1, x, 1], -P[y - 1, x, 2]
    else:
        dv0, dv1, dv2 = P[y + 1, x, 0] - P[y - 1, x, 0], P[y + 1, x, 1] - P[y - 1, x, 1], P[y + 1, x, 2] - P[y - 1, x, 2]
    return du0, du1, du2, dv0, dv1, dv2


@njit(cache=True, nogil=True)
def _normal_planes(v: np.ndarray, border: np.ndarray, P: np.ndarray, d: np.ndarray) -> np.ndarray:
    """4 x H x W float32 [w, n * w]: w = 1 where the pixel and its 4 neighbours are smooth surface, n the unit
    normal du x dv of the central differences, turned to face the camera."""
    h, wd = v.shape
    smooth = np.zeros((h + 2, wd + 2), np.bool_)  # padded with False: no neighbour outside the image
    for y in range(h):
        for x in range(wd):
            smooth[y + 1, x + 1] = v[y, x] and not border[y, x]
    out = np.empty((4, h, wd), np.float32)
    eps, zero, one = np.float32(1e-12), np.float32(0.0), np.float32(1.0)
    for y in range(h):
        for x in range(wd):
            ok = smooth[y + 1, x + 1] and smooth[y + 1, x + 2] and smooth[y + 1, x] and smooth[y + 2, x + 1] \
                and smooth[y, x + 1]
            du0, du1, du2, dv0, dv1, dv2 = _differences(P, y, x)
            n0 = du1 * dv2 - du2 * dv1
            n1 = du2 * dv0 - du0 * dv2
            n2 = du0 * dv1 - du1 * dv0
            norm = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
            den = norm if norm > eps else eps
            n0, n1, n2 = n0 / den, n1 / den, n2 / den
            if (n0 * d[y, x, 0] + n1 * d[y, x, 1]) + n2 * d[y, x, 2] > zero:
                n0, n1, n2 = -n0, -n1, -n2
            wgt = one if ok else zero
            out[0, y, x] = wgt
            out[1, y, x] = n0 * wgt
            out[2, y, x] = n1 * wgt
            out[3, y, x] = n2 * wgt
    return out


def range_normals(v: np.ndarray, z: np.ndarray, d: np.ndarray, f: float,
                  footprints: float) -> tuple[np.ndarray, np.ndarray]:
    """(border mask, 4 x H x W [w, n * w]) of the range image: narf_interest's steps 1 and 2."""
    d = np.ascontiguousarray(d, dtype=np.float32)
    rng, P = _range(v, z, d)
    border = _borders(v, rng, np.float32(f), np.float32(footprints))
    return border, _normal_planes(v, border, P, d)


@njit(cache=True, nogil=True)
def scale_split(kf: np.ndarray, v: np.ndarray, n_scales: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel its lower scale k0 = floor(kf) and blend fraction t = kf - k0 (float32), and the scales some
    valid pixel uses (as k0 or k0 + 1, clipped), ascending."""
    h, w = kf.shape
    k0 = np.empty((h, w), np.int8)
    t = np.empty((h, w), np.float32)
    count = np.zeros(n_scales, np.int64)
    for y in range(h):
        for x in range(w):
            k = int(np.floor(kf[y, x]))
            k0[y, x] = k
            t[y, x] = np.float32(np.float64(kf[y, x]) - np.float64(k))
            if v[y, x]:
                count[k] += 1
                count[min(k + 1, n_scales - 1)] += 1
    return k0, t, np.flatnonzero(count)


@njit(cache=True, nogil=True)
def blend(out: np.ndarray, k0: np.ndarray, t: np.ndarray, ki: int, top: int, value: np.ndarray) -> None:
    """out += weight * value, weight = (1 - t where k0 == ki) + (t where min(k0 + 1, top) == ki), in float32."""
    h, w = out.shape
    one, zero = np.float32(1.0), np.float32(0.0)
    for y in range(h):
        for x in range(w):
            k = k0[y, x]
            a = one - t[y, x] if k == ki else zero
            b = t[y, x] if min(k + 1, top) == ki else zero
            out[y, x] += (a + b) * value[y, x]


@njit(cache=True, nogil=True)
def tensor_planes(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """3 x H x W float32 [gx gx, gy gy, gx gy]: the structure tensor's entries before blurring."""
    h, w = gx.shape
    out = np.empty((3, h, w), np.float32)
    for y in range(h):
        for x in range(w):
            out[0, y, x] = gx[y, x] * gx[y, x]
            out[1, y, x] = gy[y, x] * gy[y, x]
            out[2, y, x] = gx[y, x] * gy[y, x]
    return out
