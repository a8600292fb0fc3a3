"""Compiled per-pixel passes of keypoints3d's NARF-like interest (keypoints.narf_interest), each the numpy
expressions it replaces bit for bit: the same float32 operations in the same order (numpy's float32 arithmetic
with Python scalars stays float32; its norm and einsum over 3 channels add left to right), without the
full-size temporaries (tests/worker/cues/test_kernels.py against tests/fixtures/reference_narf.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def _range(v: np.ndarray, z: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Euclidean range (inf off v) and camera-space points d * range as 3 x H x W planes (d * 0 off v: signed
    zeros as numpy's)."""
    h, w = v.shape
    rng = np.empty((h, w), np.float32)
    P = np.empty((3, h, w), np.float32)
    for y in range(h):
        for x in range(w):
            r = z[y, x] / d[y, x, 2] if v[y, x] else np.float32(0.0)
            rng[y, x] = r if v[y, x] else np.float32(np.inf)
            for c in range(3):
                P[c, y, x] = d[y, x, c] * r
    return rng, P


@njit(cache=True, nogil=True, error_model="numpy")
def _borders(v: np.ndarray, rng: np.ndarray, f: np.float32, footprints: np.float32) -> np.ndarray:
    """Foreground borders: a 4-neighbour (inf outside the image) farther by more than footprints * range /
    f."""
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


@njit(cache=True, nogil=True, error_model="numpy")
def _normal_planes(v: np.ndarray, border: np.ndarray, P: np.ndarray, d: np.ndarray) -> np.ndarray:
    """4 x H x W float32 [w, n * w]: w = 1 where the pixel and its 4 neighbours are smooth surface, n the unit
    normal du x dv of the central differences (P[i + 1] - P[i - 1], zeros outside), turned to face the camera.
    Row by row: the differences into row buffers, then one branch-free loop that LLVM vectorises."""
    h, wd = v.shape
    smooth = np.zeros((h + 2, wd + 2), np.bool_)  # padded with False: no neighbour outside the image
    for y in range(h):
        for x in range(wd):
            smooth[y + 1, x + 1] = v[y, x] and not border[y, x]
    out = np.empty((4, h, wd), np.float32)
    du = np.empty((3, wd), np.float32)
    dv = np.empty((3, wd), np.float32)
    weight = np.empty(wd, np.float32)
    # the row's ray directions as planes: strided loads kept the loop slow
    ray = np.empty((3, wd), np.float32)
    eps, zero, one = np.float32(1e-12), np.float32(0.0), np.float32(1.0)
    for y in range(h):
        for c in range(3):
            _differences(P[c], y, du[c], dv[c])
        mid, below, above = smooth[y + 1], smooth[y + 2], smooth[y]
        for x in range(wd):  # & rather than `and`: no branches
            weight[x] = one if mid[x + 1] & mid[x + 2] & mid[x] & below[x + 1] & above[x + 1] else zero
        du0, du1, du2, dv0, dv1, dv2 = du[0], du[1], du[2], dv[0], dv[1], dv[2]
        o0, o1, o2, o3, dy = out[0, y], out[1, y], out[2, y], out[3, y], d[y]
        for x in range(wd):
            ray[0, x], ray[1, x], ray[2, x] = dy[x, 0], dy[x, 1], dy[x, 2]
        r0, r1, r2 = ray[0], ray[1], ray[2]
        for x in range(wd):
            n0 = du1[x] * dv2[x] - du2[x] * dv1[x]
            n1 = du2[x] * dv0[x] - du0[x] * dv2[x]
            n2 = du0[x] * dv1[x] - du1[x] * dv0[x]
            norm = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
            den = norm if norm > eps else eps
            n0, n1, n2 = n0 / den, n1 / den, n2 / den
            flip = (n0 * r0[x] + n1 * r1[x]) + n2 * r2[x] > zero
            n0 = -n0 if flip else n0
            n1 = -n1 if flip else n1
            n2 = -n2 if flip else n2
            wgt = weight[x]
            o0[x] = wgt
            o1[x] = n0 * wgt
            o2[x] = n1 * wgt
            o3[x] = n2 * wgt
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _differences(plane: np.ndarray, y: int, du: np.ndarray, dv: np.ndarray) -> None:
    """Row y of plane[i + 1] - plane[i - 1] along x (du) and y (dv), zeros outside the image."""
    h, w = plane.shape
    row = plane[y]
    du[0] = row[1]
    du[w - 1] = -row[w - 2]
    left, right, inner = row[0:w - 2], row[2:w], du[1:w - 1]
    for x in range(w - 2):
        inner[x] = right[x] - left[x]
    if y == 0:
        nxt = plane[1]
        for x in range(w):
            dv[x] = nxt[x]
    elif y == h - 1:
        prv = plane[y - 1]
        for x in range(w):
            dv[x] = -prv[x]
    else:
        nxt, prv = plane[y + 1], plane[y - 1]
        for x in range(w):
            dv[x] = nxt[x] - prv[x]


def range_normals(v: np.ndarray, z: np.ndarray, d: np.ndarray, f: float,
                  footprints: float) -> tuple[np.ndarray, np.ndarray]:
    """(border mask, 4 x H x W [w, n * w]) of the range image: narf_interest's steps 1 and 2."""
    d = np.ascontiguousarray(d, dtype=np.float32)
    rng, P = _range(v, z, d)
    border = _borders(v, rng, np.float32(f), np.float32(footprints))
    return border, _normal_planes(v, border, P, d)


@njit(cache=True, nogil=True, error_model="numpy")
def support_px(v: np.ndarray, z: np.ndarray, fs: np.float32) -> np.ndarray:
    """maximum(fs / where(v, z, inf), 1e-6) in float32: the support size in pixels (fs = f * support in
    metres), 1e-6 off v (numpy's maximum keeps a NaN)."""
    h, w = v.shape
    out = np.empty((h, w), np.float32)
    tiny = np.float32(1e-6)
    off = fs / np.float32(np.inf)
    for y in range(h):
        vy, zy, o = v[y], z[y], out[y]
        for x in range(w):
            s = fs / zy[x]  # every pixel, then chosen: a loop LLVM vectorises
            s = s if vy[x] else off
            o[x] = tiny if s < tiny else s
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def scale_split(kf: np.ndarray, v: np.ndarray, n_scales: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """kf clipped to 0..n_scales - 1 (numpy's clip: NaN kept, the bound on ties), then per pixel its lower
    scale k0 = floor(kf) and blend fraction t = kf - k0 (float32), and the scales some valid pixel uses (as
    k0 or k0 + 1, clipped), ascending."""
    h, w = kf.shape
    k0 = np.empty((h, w), np.int8)
    t = np.empty((h, w), np.float32)
    count = np.zeros(n_scales, np.int64)
    lo, hi = np.float32(0.0), np.float32(n_scales - 1)
    for y in range(h):
        ky, ty, vy, row = k0[y], t[y], v[y], kf[y]
        for x in range(w):
            c = row[x]
            c = lo if c <= lo else c
            c = hi if c >= hi else c
            fl = np.floor(c)
            ky[x] = np.int8(fl)
            ty[x] = np.float32(np.float64(c) - np.float64(fl))
        for x in range(w):
            if vy[x]:
                count[ky[x]] += 1
                count[min(ky[x] + 1, n_scales - 1)] += 1
    return k0, t, np.flatnonzero(count)


@njit(cache=True, nogil=True, error_model="numpy")
def blend(out: np.ndarray, k0: np.ndarray, t: np.ndarray, ki: int, top: int, value: np.ndarray) -> None:
    """out += weight * value, weight = (1 - t where k0 == ki) + (t where min(k0 + 1, top) == ki), in
    float32."""
    h, w = out.shape
    one, zero = np.float32(1.0), np.float32(0.0)
    for y in range(h):
        for x in range(w):
            k = k0[y, x]
            a = one - t[y, x] if k == ki else zero
            b = t[y, x] if min(k + 1, top) == ki else zero
            out[y, x] += (a + b) * value[y, x]


@njit(cache=True, nogil=True, error_model="numpy")
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


@njit(cache=True, nogil=True, error_model="numpy")
def half_means(x: np.ndarray) -> np.ndarray:
    """2 x 2 block means of a C x H x W float32 array, edge-padded to even size: ((x00 + x10) + x01 + x11) *
    0.25 in float32, the order numpy's sum of the four strided slices took."""
    c, h, w = x.shape
    hh, hw = (h + 1) // 2, (w + 1) // 2
    out = np.empty((c, hh, hw), np.float32)
    quarter = np.float32(0.25)
    for p in range(c):
        for i in range(hh):
            top, bottom, o = x[p, 2 * i], x[p, min(2 * i + 1, h - 1)], out[p, i]
            for j in range(w // 2):
                o[j] = (((top[2 * j] + bottom[2 * j]) + top[2 * j + 1]) + bottom[2 * j + 1]) * quarter
            if w % 2:  # the last column edge-padded
                o[hw - 1] = (((top[w - 1] + bottom[w - 1]) + top[w - 1]) + bottom[w - 1]) * quarter
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def double(x: np.ndarray) -> np.ndarray:
    """Bilinear 2x upsampling at pixel centres of an H x W float32 array, C order: rows first (row 2i + a of
    0.75 x[i] + 0.25 x[i -+ 1], clamped), then columns alike, each output c + 0.25 neighbour with c = 0.75 x
    in float32 (keypoints' two transposed passes, bit for bit, without the transposes)."""
    n, m = x.shape
    near, far = np.float32(0.75), np.float32(0.25)
    out = np.empty((2 * n, 2 * m), np.float32)
    row = np.empty(m, np.float32)
    for i in range(n):
        for a in range(2):
            src, nb = x[i], x[max(i - 1, 0) if a == 0 else min(i + 1, n - 1)]
            for j in range(m):
                row[j] = near * src[j] + far * nb[j]
            o = out[2 * i + a]
            # the clamped ends apart: the inner loop's unclamped neighbours let LLVM vectorise it
            for j in (0, m - 1):
                c = near * row[j]
                o[2 * j] = c + far * row[max(j - 1, 0)]
                o[2 * j + 1] = c + far * row[min(j + 1, m - 1)]
            if m > 2:
                mid, left, right, even, odd = row[1:m - 1], row[0:m - 2], row[2:m], o[2:2 * m - 2:2], \
                    o[3:2 * m - 2:2]
                for j in range(m - 2):
                    c = near * mid[j]
                    even[j] = c + far * left[j]
                    odd[j] = c + far * right[j]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def surface_change(b: np.ndarray) -> np.ndarray:
    """Spread of the mean normal sqrt(clip(1 - |m|^2, 0, 1)), m = b[1:] / max(b[0], 1e-6), 0 where b[0] <=
    1e-6, from b = the blurred [w, n * w]: numpy's float32 steps per pixel (maximum and clip give their second
    operand on ties, keep NaN; einsum adds the channels in order)."""
    _, h, w = b.shape
    out = np.empty((h, w), np.float32)
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-6)
    for y in range(h):
        cnt, b1, b2, b3, o = b[0, y], b[1, y], b[2, y], b[3, y], out[y]
        for x in range(w):
            c = cnt[x]
            den = c if c > tiny or np.isnan(c) else tiny
            m1, m2, m3 = b1[x] / den, b2[x] / den, b3[x] / den
            v = one - ((m1 * m1 + m2 * m2) + m3 * m3)
            v = v if v > zero or np.isnan(v) else zero
            v = v if v < one or np.isnan(v) else one
            o[x] = np.sqrt(v) if c > tiny else zero
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def isotropy(b: np.ndarray) -> np.ndarray:
    """2 max(lo, 0) / max(lo + hi, 1e-12) of the eigenvalues lo, hi = tr/2 -+ sqrt(max((a - b)^2 / 4 + c^2,
    0)) of b = the blurred structure tensor [a, b, c], 0 where tr <= 1e-6: numpy's float32 steps per pixel."""
    _, h, w = b.shape
    out = np.empty((h, w), np.float32)
    zero, two, four, tiny, eps = np.float32(0.0), np.float32(2.0), np.float32(4.0), np.float32(1e-6), \
        np.float32(1e-12)
    for y in range(h):
        ra, rb, rc, o = b[0, y], b[1, y], b[2, y], out[y]
        for x in range(w):
            a, bb, c = ra[x], rb[x], rc[x]
            tr = a + bb
            diff = a - bb
            q = (diff * diff) / four + c * c
            disc = np.sqrt(q if q > zero or np.isnan(q) else zero)
            half = tr / two
            lo, hi = half - disc, half + disc
            num = two * (lo if lo > zero or np.isnan(lo) else zero)
            s = lo + hi
            o[x] = num / (s if s > eps or np.isnan(s) else eps) if tr > tiny else zero
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def mark_borders(change: np.ndarray, border: np.ndarray, v: np.ndarray) -> None:
    """In place: change = 1 on borders, then 0 off valid depth."""
    h, w = change.shape
    for y in range(h):
        for x in range(w):
            if not v[y, x]:
                change[y, x] = 0.0
            elif border[y, x]:
                change[y, x] = 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def interest(change: np.ndarray, iso: np.ndarray, v: np.ndarray) -> np.ndarray:
    """clip(change * iso, 0, 1) with iso 0 off valid depth, in float32 (clip gives its bound on ties, keeps
    NaN)."""
    h, w = change.shape
    out = np.empty((h, w), np.float32)
    zero, one = np.float32(0.0), np.float32(1.0)
    for y in range(h):
        c, i, m, o = change[y], iso[y], v[y], out[y]
        for x in range(w):
            p = c[x] * (i[x] if m[x] else zero)
            p = p if p > zero or np.isnan(p) else zero
            o[x] = p if p < one or np.isnan(p) else one
    return out
