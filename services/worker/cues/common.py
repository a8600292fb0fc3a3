"""Per-view intermediates shared by several cues, each memoised in the ViewContext.

Frames: `normal_cam` uses the Omnidata camera axes for normals (x right, y up, z towards the viewer);
`ray_dirs_cam` uses OpenCV camera axes (x right, y down, z forward). Depth in metres.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from services.core.domain.cues import UINT16_NONE
from services.worker.context import ViewContext


def hit(ctx: ViewContext) -> np.ndarray:
    """bool H x W: some surface is seen (regardless of max depth)."""
    return ctx.memo("hit", lambda: ctx.passes.hit)


def depth_m(ctx: ViewContext) -> np.ndarray:
    """float32 H x W optical-axis depth in metres, inf where nothing is seen."""
    return ctx.passes.depth_z


def ray_dirs_cam64(ctx: ViewContext) -> np.ndarray:
    """float64 H x W x 3 unit pixel-centre ray directions, OpenCV camera axes (ViewGeometry.ray_directions_cam)."""
    return ctx.memo("ray_dirs_cam64", ctx.geometry.ray_directions_cam)


def ray_dirs_cam(ctx: ViewContext) -> np.ndarray:
    """float32 H x W x 3 unit pixel-centre ray directions, OpenCV camera axes."""
    return ctx.memo("ray_dirs_cam", lambda: ray_dirs_cam64(ctx).astype(np.float32))


def position_world(ctx: ViewContext) -> np.ndarray:
    """float32 H x W x 3 world position (metres) of the seen surface, NaN = none: ViewPasses.position_world's
    arithmetic (float64, cast at the end) on the view's memoised rays."""
    g = ctx.geometry
    d_cam = ray_dirs_cam64(ctx)
    return _position_world(depth_m(ctx), d_cam, d_cam @ g.rotation, np.asarray(g.center, dtype=np.float64), hit(ctx))


@njit(cache=True, nogil=True)
def _position_world(depth: np.ndarray, d_cam: np.ndarray, d_world: np.ndarray, center: np.ndarray,
                    hit: np.ndarray) -> np.ndarray:
    """centre + d_world * (depth / d_cam.z) per pixel in float64, cast to float32, NaN where nothing is hit: numpy's
    operations one pixel at a time (the same roundings, ~5x less CPU than the whole-array temporaries); the matrix
    product d_world = d_cam @ R stays numpy's."""
    h, w = depth.shape
    out = np.empty((h, w, 3), np.float32)
    for y in range(h):
        for x in range(w):
            if not hit[y, x]:
                out[y, x, 0] = out[y, x, 1] = out[y, x, 2] = np.float32(np.nan)
                continue
            t = np.float64(depth[y, x]) / d_cam[y, x, 2]  # euclidean distance along the unit ray
            for k in range(3):
                out[y, x, k] = np.float32(center[k] + d_world[y, x, k] * t)
    return out


def euclidean_m(ctx: ViewContext) -> np.ndarray:
    """float32 H x W distance from the camera centre in metres (z / cos of the ray's angle to the axis), inf = none."""
    return ctx.memo("euclidean_m", lambda: (depth_m(ctx) / ray_dirs_cam(ctx)[..., 2]).astype(np.float32))


def valid(ctx: ViewContext) -> np.ndarray:
    """bool H x W: depth is representable: a surface, z <= max_depth_m, and round(z * units) <= 65534."""

    def compute() -> np.ndarray:
        p = ctx.params
        z = depth_m(ctx)
        with np.errstate(invalid="ignore", over="ignore"):
            return hit(ctx) & (z <= p.max_depth_m) & (np.rint(z * p.depth_units_per_m) < UINT16_NONE)

    return ctx.memo("valid", compute)


def to_uint16_depth(ctx: ViewContext, metres: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """round(metres * units) as uint16 where mask (and representable), 65535 elsewhere."""
    with np.errstate(invalid="ignore", over="ignore"):
        q = np.rint(np.where(mask, metres, 0.0) * ctx.params.depth_units_per_m)
    ok = mask & (q < UINT16_NONE)
    return np.where(ok, q, UINT16_NONE).astype(np.uint16)


def normal_cam(ctx: ViewContext) -> np.ndarray:
    """float32 H x W x 3 unit normals in camera axes x right, y up, z towards the viewer; 0 where no surface."""

    def compute() -> np.ndarray:
        R = ctx.geometry.rotation.astype(np.float32)
        n_cv = ctx.passes.require("normal_world") @ R.T  # world -> OpenCV camera axes
        # Face the camera: Cycles already flips back-facing hits; this guards interpolated or user normals.
        facing = np.einsum("hwc,hwc->hw", n_cv, ray_dirs_cam(ctx)) > 0
        # Turning (-1 where facing) and the OpenCV (x right, y down, z fwd) -> DESIGN axes flip in one exact
        # multiplication by +-1 per pixel and channel.
        sign = np.where(facing, np.float32(-1.0), np.float32(1.0))[..., None] * np.array([1.0, -1.0, -1.0],
                                                                                          dtype=np.float32)
        return np.where(hit(ctx)[..., None], n_cv * sign, np.float32(0.0))

    return ctx.memo("normal_cam", compute)


def grey(ctx: ViewContext) -> np.ndarray:
    """float32 H x W luma (Rec. 601 weights) of the 8-bit sRGB colour, in [0, 1]."""

    def compute() -> np.ndarray:
        rgb = ctx.passes.rgb.astype(np.float32)
        return (rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)) / 255.0

    return ctx.memo("grey", compute)


def sobel_magnitude(img: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude (scipy's unnormalised 3x3 kernels: a unit step gives 4), float32."""
    gx, gy = sobel_xy(img)
    return np.hypot(gx, gy).astype(np.float32)


def sobel_xy(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """scipy.ndimage.sobel(img, axis=1 and axis=0, mode="nearest") of an H x W float32 image, bit for bit (scipy's
    two correlate1d passes each, [-1, 0, 1] then [1, 2, 1], in float64 rounded to float32 after each), compiled;
    other inputs go to scipy."""
    if img.dtype != np.float32 or img.ndim != 2:
        from scipy.ndimage import sobel

        return sobel(img, axis=1, mode="nearest"), sobel(img, axis=0, mode="nearest")
    return _sobel_xy(np.ascontiguousarray(img))


@njit(cache=True, nogil=True)
def _sobel_xy(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h, w = img.shape
    dx = np.empty((h, w), np.float32)  # [-1, 0, 1] along x (scipy's antisymmetric loop: x0 * 0 + (x-1 - x+1) * -1)
    dy = np.empty((h, w), np.float32)
    for y in range(h):
        ym, yp = max(y - 1, 0), min(y + 1, h - 1)
        for x in range(w):
            xm, xp = max(x - 1, 0), min(x + 1, w - 1)
            c = np.float64(img[y, x]) * 0.0
            dx[y, x] = np.float32(c + (np.float64(img[y, xm]) - np.float64(img[y, xp])) * -1.0)
            dy[y, x] = np.float32(c + (np.float64(img[ym, x]) - np.float64(img[yp, x])) * -1.0)
    gx = np.empty((h, w), np.float32)  # then [1, 2, 1] across (scipy's symmetric loop: x0 * 2 + (x-1 + x+1) * 1)
    gy = np.empty((h, w), np.float32)
    for y in range(h):
        ym, yp = max(y - 1, 0), min(y + 1, h - 1)
        for x in range(w):
            xm, xp = max(x - 1, 0), min(x + 1, w - 1)
            gx[y, x] = np.float32(np.float64(dx[y, x]) * 2.0 + (np.float64(dx[ym, x]) + np.float64(dx[yp, x])) * 1.0)
            gy[y, x] = np.float32(np.float64(dy[y, x]) * 2.0 + (np.float64(dy[y, xm]) + np.float64(dy[y, xp])) * 1.0)
    return gx, gy


def to_uint16_scaled(values: np.ndarray, scale: float) -> np.ndarray:
    """round(values * scale) clipped to 0..65535, uint16."""
    return np.clip(np.rint(values * scale), 0, 65535).astype(np.uint16)


GAUSS_NEAREST, GAUSS_REFLECT = 0, 1  # scipy.ndimage modes "nearest" (edge repeated) and "reflect" (half-sample)
# ("constant", zeros outside, runs as "nearest" on a zero-padded copy)


def gaussian_blur(img: np.ndarray, sigma: float, truncate: float = 4.0, mode: str = "nearest") -> np.ndarray:
    """scipy.ndimage.gaussian_filter(img, sigma, mode=mode, truncate=truncate) of an H x W float32 image, bit for
    bit: the same kernel, taps added in the order scipy's symmetric correlate1d adds them (in float64, rounded to
    float32 after each axis, rows first), as compiled loops over whole rows (about 2x faster than scipy's per-line
    buffers at 512 px). Other inputs (dtype, shape, a kernel wider than a reflected image) go to scipy."""
    from scipy.ndimage import gaussian_filter

    radius = int(truncate * float(sigma) + 0.5)
    if img.dtype != np.float32 or img.ndim != 2 or sigma <= 0 or mode not in ("nearest", "reflect", "constant") \
            or (mode == "reflect" and radius >= min(img.shape)):
        return gaussian_filter(img, sigma, mode=mode, truncate=truncate)
    x = np.arange(-radius, radius + 1)
    taps = np.exp(-0.5 / (sigma * sigma) * x**2)  # scipy's _gaussian_kernel1d, order 0
    taps = taps / taps.sum()
    if mode == "constant":  # zeros outside (cval 0): a zero border as wide as the kernel, then cropped
        h, w = img.shape
        padded = np.pad(img, radius)
        out = _blur_cols(_blur_rows(padded, taps, GAUSS_NEAREST), taps, GAUSS_NEAREST)
        return np.ascontiguousarray(out[radius:radius + h, radius:radius + w])
    code = GAUSS_NEAREST if mode == "nearest" else GAUSS_REFLECT
    return _blur_cols(_blur_rows(np.ascontiguousarray(img), taps, code), taps, code)


@njit(cache=True, nogil=True)
def _extend(i: int, n: int, mode: int) -> int:
    if mode == GAUSS_NEAREST:
        return min(max(i, 0), n - 1)
    return -i - 1 if i < 0 else (2 * n - i - 1 if i >= n else i)


@njit(cache=True, nogil=True)
def _blur_rows(img: np.ndarray, taps: np.ndarray, mode: int) -> np.ndarray:
    """Along axis 0: out = x[0] w[0] + sum over j = -r..-1 of (x[j] + x[-j]) w[j], in float64, as scipy."""
    h, w = img.shape
    r = len(taps) // 2
    out = np.empty((h, w), np.float32)
    acc = np.empty(w, np.float64)
    for y in range(h):
        for x in range(w):
            acc[x] = np.float64(img[y, x]) * taps[r]
        for j in range(-r, 0):
            ya, yb, wj = _extend(y + j, h, mode), _extend(y - j, h, mode), taps[r + j]
            for x in range(w):
                acc[x] += (np.float64(img[ya, x]) + np.float64(img[yb, x])) * wj
        for x in range(w):
            out[y, x] = np.float32(acc[x])
    return out


_COL_BLOCK = 16  # rows blurred together along x: longer inner loops over a block, ~1.3x faster than row by row


@njit(cache=True, nogil=True)
def _blur_cols(img: np.ndarray, taps: np.ndarray, mode: int) -> np.ndarray:
    """Along axis 1, the same sums on extended copies of the rows, a block of rows at a time."""
    h, w = img.shape
    r = len(taps) // 2
    out = np.empty((h, w), np.float32)
    line = np.empty((_COL_BLOCK, w + 2 * r), np.float64)
    acc = np.empty((_COL_BLOCK, w), np.float64)
    for y0 in range(0, h, _COL_BLOCK):
        nb = min(_COL_BLOCK, h - y0)
        for b in range(nb):
            for x in range(w):
                line[b, x + r] = img[y0 + b, x]
            for x in range(r):
                line[b, x] = img[y0 + b, _extend(x - r, w, mode)]
                line[b, w + r + x] = img[y0 + b, _extend(w + x, w, mode)]
            for x in range(w):
                acc[b, x] = line[b, x + r] * taps[r]
        for j in range(-r, 0):
            wj = taps[r + j]
            for b in range(nb):
                for x in range(w):
                    acc[b, x] += (line[b, x + r + j] + line[b, x + r - j]) * wj
        for b in range(nb):
            for x in range(w):
                out[y0 + b, x] = np.float32(acc[b, x])
    return out
