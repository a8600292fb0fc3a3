"""Keypoint cues (16-bit PNGs): 2D blob response on the colour image, 3D interest on the range image.

keypoints2d: max over scales s in keypoints2d_sigmas (px) of the scale-normalised determinant of the Hessian
s^4 (Lxx Lyy - Lxy^2) of the Gaussian-blurred grey image in [0, 1] (blurred incrementally from scale to scale,
kernels cut at 3 sigmas, second derivatives by central differences), negative responses (saddles) set to 0,
stored as round(response * keypoints2d_scale) clipped to 0..65535. Whole image, like the other image-space
cues.

keypoints3d: a NARF-like interest image (Steder et al., "Point feature extraction on 3D range scans taking
into account object boundaries", ICRA 2011), computed from the depth image and the intrinsics only:
1. Range image: back-project every valid pixel to camera coordinates (metres); normals from central
   differences of the 3D points, turned to face the camera.
2. Borders: a pixel is a foreground border when a 4-neighbour is invalid or farther by more than 10 pixel
   footprints (10 * range / f): the surface behind is occluded there.
3. Surface change: the support radius keypoints3d_support_m is converted to pixels per pixel (f * support / z)
   and placed between the two nearest scales of 1, 2, 4, ... 64 px (linear blend in log2); at a scale, change
   = sqrt(1 - |mean normal|^2) over a window of that radius (near-Gaussian, sigma ~ radius/2, three box
   passes) (0 on a plane, towards 1 where normals spread); borders count 1.
4. Directional variety (NARF's "interest"): the structure tensor of the surface-change gradient, averaged over
   the same window, gives isotropy = 2 lambda_min / (lambda_max + lambda_min): ~0 along a straight fold or
   border (change in one direction only), ~1 at corners and blobs (change in several directions).
5. interest = change * isotropy in [0, 1], 0 where depth is invalid; stored as round(interest * 65535).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import njit
from scipy.ndimage import uniform_filter

from services.worker.context import ViewContext
from services.worker.cues.common import (
    depth_m,
    gaussian_blur,
    grey,
    ray_dirs_cam,
    sobel_xy,
    to_uint16_scaled,
    valid,
)
from services.worker.cues.narf_kernels import (
    blend,
    double,
    half_means,
    interest,
    isotropy,
    mark_borders,
    range_normals,
    scale_split,
    support_px,
    surface_change,
    tensor_planes,
)
from services.worker.cues.registry import register

KP3D_SCALES_PX = (1, 2, 4, 8, 16, 32, 64)
# keypoints2d's Gaussian kernels end at 3 sigmas (scipy's default is 4): 25% fewer taps, the 0.3% of weight
# past 3 sigmas moves responses by ~2% (tests/worker/cues/test_equivalence.py).
DOH_TRUNCATE_SIGMAS = 3.0
BORDER_FOOTPRINTS = 10.0
PYRAMID_MIN_RADIUS_PX = 4  # wider blurs run on block means (a radius of >= 4 low-res pixels), then upsampled


def doh_response(g: np.ndarray, sigmas: tuple[float, ...]) -> np.ndarray:
    """float32 H x W max over scales of the scale-normalised determinant of Hessian (>= 0)."""
    out = np.zeros(g.shape, dtype=np.float32)
    L, prev = g.astype(np.float32), 0.0
    for s in sorted(sigmas):
        inc = float(np.sqrt(max(s * s - prev * prev, 0.0)))
        if inc > 0:
            L = gaussian_blur(L, inc, DOH_TRUNCATE_SIGMAS)
        prev = s
        _max_doh(L, np.float32(s**4), out)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _max_doh(L: np.ndarray, s4: np.float32, out: np.ndarray) -> None:
    """out = max(out, s4 * (lxx lyy - lxy^2)) with central differences of L (edges clamped), in float32 and in
    the order numpy's in-place version took (so the values are the same bit for bit), fused in one pass: row
    by row over row slices, the clamped first and last columns apart (the unclamped inner loop vectorises)."""
    h, w = L.shape
    for y in range(h):
        up, row, down, o = L[max(y - 1, 0)], L[y], L[min(y + 1, h - 1)], out[y]
        if w > 2:
            _doh_row(row[1:w - 1], row[0:w - 2], row[2:w], up[1:w - 1], up[0:w - 2], up[2:w], down[1:w - 1],
                     down[0:w - 2], down[2:w], s4, o[1:w - 1])
        for x in (0, w - 1):
            xm, xp = max(x - 1, 0), min(x + 1, w - 1)
            _doh_row(row[x:x + 1], row[xm:xm + 1], row[xp:xp + 1], up[x:x + 1], up[xm:xm + 1], up[xp:xp + 1],
                     down[x:x + 1], down[xm:xm + 1], down[xp:xp + 1], s4, o[x:x + 1])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _doh_row(
    c: np.ndarray, left: np.ndarray, right: np.ndarray, up: np.ndarray, up_left: np.ndarray,
    up_right: np.ndarray, down: np.ndarray, down_left: np.ndarray, down_right: np.ndarray, s4: np.float32,
    out: np.ndarray,
) -> None:
    two, sixteenth = np.float32(2.0), np.float32(0.0625)
    for x in range(len(c)):
        lxx = (right[x] + left[x]) - two * c[x]
        lyy = (down[x] + up[x]) - two * c[x]
        lxy = ((down_right[x] - down_left[x]) - up_right[x]) + up_left[x]  # 4 x the mixed derivative
        v = (lxx * lyy - (lxy * lxy) * sixteenth) * s4
        if v > out[x]:
            out[x] = v


@register("keypoints2d")
def keypoints2d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W multi-scale determinant-of-Hessian blob response of the grey image."""
    r = doh_response(grey(ctx), tuple(ctx.params.keypoints2d_sigmas))
    return to_uint16_scaled(r, ctx.params.keypoints2d_scale)


def _blur(x: np.ndarray, radius_px: int) -> np.ndarray:
    """Approximately Gaussian blur with sigma ~ radius/2: three box passes of width ~radius (O(1) per pixel).

    x is H x W, or C x H x W (channel planes blurred independently). The passes are scipy's uniform_filter
    (mode "constant") bit for bit: its running sums in float64, rounded to float32 after each axis, as
    compiled loops (~3x faster than scipy's per-line buffers); inputs other than float32 go to scipy
    itself."""
    size = max(1, int(radius_px)) | 1
    if x.dtype != np.float32:
        sizes = (1,) * (x.ndim - 2) + (size, size)
        for _ in range(3):
            x = uniform_filter(x, sizes, mode="constant")
        return x
    planes = np.ascontiguousarray(x).reshape((-1,) + x.shape[-2:])
    out = np.empty_like(planes)
    for c, plane in enumerate(planes):
        for _ in range(3):
            plane = _box_cols(_box_rows(plane, size), size)
        out[c] = plane
    return out.reshape(x.shape)


@njit(cache=True, nogil=True, error_model="numpy")
def _box_rows(img: np.ndarray, size: int) -> np.ndarray:
    """Mean over `size` rows centred on each pixel, zeros outside: scipy's running sum (sum += new - old)."""
    h, w = img.shape
    r = size // 2
    out = np.empty((h, w), np.float32)
    total = np.zeros(w, np.float64)
    for y in range(-r, size - r):
        if 0 <= y < h:
            for x in range(w):
                total[x] += np.float64(img[y, x])
    for x in range(w):
        out[0, x] = np.float32(total[x] / size)
    for y in range(1, h):
        y_in, y_out = y + size - 1 - r, y - 1 - r
        for x in range(w):
            new = np.float64(img[y_in, x]) if y_in < h else 0.0
            old = np.float64(img[y_out, x]) if y_out >= 0 else 0.0
            total[x] += new - old
            out[y, x] = np.float32(total[x] / size)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _box_cols(img: np.ndarray, size: int) -> np.ndarray:
    """Mean over `size` columns centred on each pixel, zeros outside (scipy's running sum along a line). Four
    rows at a time: their running sums are independent chains the CPU overlaps, and the divisions run
    afterwards as a vectorised loop over the row (~1.7x faster than one row at a time)."""
    h, w = img.shape
    r = size // 2
    out = np.empty((h, w), np.float32)
    line = np.zeros((4, w + size), np.float64)  # rows with `r` zeros before and `size - r` after
    sums = np.empty((4, w), np.float64)
    fsize = np.float64(size)
    for y0 in range(0, h, 4):
        nb = min(4, h - y0)
        for b in range(4):
            dst = line[b, r:r + w]
            if b < nb:
                row = img[y0 + b]
                for x in range(w):
                    dst[x] = row[x]
            else:
                dst[:] = 0.0
        l0, l1, l2, l3 = line[0], line[1], line[2], line[3]
        t0 = t1 = t2 = t3 = 0.0
        for k in range(size):
            t0 += l0[k]
            t1 += l1[k]
            t2 += l2[k]
            t3 += l3[k]
        s0, s1, s2, s3 = sums[0], sums[1], sums[2], sums[3]
        s0[0], s1[0], s2[0], s3[0] = t0, t1, t2, t3
        n0, n1, n2, n3 = l0[size - 1:], l1[size - 1:], l2[size - 1:], l3[size - 1:]
        for x in range(1, w):  # sum += new - old
            t0 += n0[x] - l0[x - 1]
            t1 += n1[x] - l1[x - 1]
            t2 += n2[x] - l2[x - 1]
            t3 += n3[x] - l3[x - 1]
            s0[x], s1[x], s2[x], s3[x] = t0, t1, t2, t3
        for b in range(nb):
            sb, ob = sums[b], out[y0 + b]
            for x in range(w):
                ob[x] = np.float32(sb[x] / fsize)
    return out


def _half(x: np.ndarray) -> np.ndarray:
    """2 x 2 block means of a C x H x W float32 array (edge-padded to even size), one compiled pass."""
    return half_means(np.ascontiguousarray(x, dtype=np.float32))


def _double(x: np.ndarray) -> np.ndarray:
    """Bilinear 2x upsampling at pixel centres (weights 3/4, 1/4; edges clamped) of an H x W float32 array:
    rows first, then columns, each output 0.75 * x + 0.25 * neighbour in float32 (one compiled pass, C
    order)."""
    return double(np.ascontiguousarray(x, dtype=np.float32))


class _Pyramid:
    """Blurs of one C x H x W image at several radii, the wide ones computed on 2^k x 2^k block means.

    A blur of radius r (three box passes of width r | 1: variance 3 ((r|1)^2 - 1) / 12 px^2) runs at the level
    f = 2^k <= r / PYRAMID_MIN_RADIUS_PX as a Gaussian of the same variance less what the block means and the
    bilinear upsampling add, so the result keeps the blur's width; fields blurred that wide are smooth at f.
    """

    def __init__(self, x: np.ndarray):
        self.shape = x.shape[1:]
        self.levels = [x]

    def level(self, k: int) -> np.ndarray:
        while len(self.levels) <= k:
            self.levels.append(_half(self.levels[-1]))
        return self.levels[k]

    def blurred(self, radius_px: int, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """fn(blur(x, radius)) at full resolution (fn maps C x H x W to H x W, applied before upsampling)."""
        k = max(0, int(np.log2(max(1, int(radius_px)) // PYRAMID_MIN_RADIUS_PX or 1)))
        if k == 0:
            return fn(_blur(self.levels[0], radius_px))
        f = 2**k
        size = max(1, int(radius_px)) | 1
        var = 3 * (size * size - 1) / 12 - (f * f - 1) / 12 - f * f / 8  # less block means and upsampling
        sigma = float(np.sqrt(max(var, 1.0)) / f)
        low = np.stack([gaussian_blur(plane, sigma, mode="constant") for plane in self.level(k)])
        out = fn(low)
        for _ in range(k):
            out = _double(out)
        return out[:self.shape[0], :self.shape[1]]


def _surface_change(b: np.ndarray) -> np.ndarray:
    """Spread of the mean normal, from b = the blurred [w, n * w] (0 where no surface was averaged)."""
    return surface_change(np.ascontiguousarray(b, dtype=np.float32))


def _isotropy(b: np.ndarray) -> np.ndarray:
    """2 x the smaller eigenvalue over the trace of b = the blurred structure tensor [jxx, jyy, jxy]."""
    return isotropy(np.ascontiguousarray(b, dtype=np.float32))


def narf_interest(ctx: ViewContext) -> np.ndarray:
    """float32 H x W NARF-like interest in [0, 1] (module docstring), 0 off valid depth. The per-pixel steps
    run as compiled passes (narf_kernels: the numpy expressions they replaced, bit for bit)."""
    v = valid(ctx)
    if not v.any():
        return np.zeros(v.shape, dtype=np.float32)
    f = float(ctx.geometry.K[0, 0])
    z = np.asarray(depth_m(ctx), dtype=np.float32)  # read where v only
    # 1./2. foreground borders, and normals from central differences where a pixel and its 4 neighbours are
    # smooth surface: the planes [w, n * w] the surface change averages.
    border, wn_planes = range_normals(v, z, ray_dirs_cam(ctx), f, BORDER_FOOTPRINTS)
    # 3./4. per-pixel scale from the metric support size, blended linearly in log2 between the two nearest
    # scales so the image has no seams where the depth crosses a scale boundary (numpy's log2: its float32
    # values, not libm's).
    kf = support_px(v, z, np.float32(f * ctx.params.keypoints3d_support_m))
    np.log2(kf, out=kf)
    k0, t, used = scale_split(kf, v, len(KP3D_SCALES_PX))
    top = len(KP3D_SCALES_PX) - 1
    wn = _Pyramid(wn_planes)
    change = np.zeros(v.shape, dtype=np.float32)
    for ki in used:
        blend(change, k0, t, int(ki), top, wn.blurred(KP3D_SCALES_PX[ki], _surface_change))
    mark_borders(change, border, v)
    gx, gy = sobel_xy(change)
    tensor = _Pyramid(tensor_planes(gx, gy))
    iso = np.zeros(v.shape, dtype=np.float32)
    for ki in used:
        blend(iso, k0, t, int(ki), top, tensor.blurred(KP3D_SCALES_PX[ki], _isotropy))
    return interest(change, iso, v)


@register("keypoints3d")
def keypoints3d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W NARF-like 3D interest from the range image: round(interest * 65535)."""
    return to_uint16_scaled(ctx.memo("narf_interest", lambda: narf_interest(ctx)), 65535.0)
