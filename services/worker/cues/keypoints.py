"""Keypoint cues (16-bit PNGs): 2D blob response on the colour image, 3D interest on the range image.

keypoints2d: max over scales s in keypoints2d_sigmas (px) of the scale-normalised determinant of the Hessian
s^4 (Lxx Lyy - Lxy^2) of the Gaussian-blurred grey image in [0, 1] (blurred incrementally from scale to scale,
second derivatives by central differences), negative responses (saddles) set to 0, stored as
round(response * keypoints2d_scale) clipped to 0..65535. Whole image, like the other image-space cues.

keypoints3d: a NARF-like interest image (Steder et al., "Point feature extraction on 3D range scans taking into
account object boundaries", ICRA 2011), computed from the depth image and the intrinsics only:
1. Range image: back-project every valid pixel to camera coordinates (metres); normals from central differences
   of the 3D points, turned to face the camera.
2. Borders: a pixel is a foreground border when a 4-neighbour is invalid or farther by more than 10 pixel
   footprints (10 * range / f): the surface behind is occluded there.
3. Surface change: the support radius keypoints3d_support_m is converted to pixels per pixel (f * support / z)
   and placed between the two nearest scales of 1, 2, 4, ... 64 px (linear blend in log2); at a scale, change =
   sqrt(1 - |mean normal|^2) over a window of that radius (near-Gaussian, sigma ~ radius/2, three box passes) (0 on a plane, towards 1 where normals spread); borders count 1.
4. Directional variety (NARF's "interest"): the structure tensor of the surface-change gradient, averaged over the
   same window, gives isotropy = 2 lambda_min / (lambda_max + lambda_min): ~0 along a straight fold or border
   (change in one direction only), ~1 at corners and blobs (change in several directions).
5. interest = change * isotropy in [0, 1], 0 where depth is invalid; stored as round(interest * 65535).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, sobel, uniform_filter

from services.worker.context import ViewContext
from services.worker.cues.common import depth_m, grey, ray_dirs_cam, to_uint16_scaled, valid
from services.worker.cues.registry import register

KP3D_SCALES_PX = (1, 2, 4, 8, 16, 32, 64)
BORDER_FOOTPRINTS = 10.0


def doh_response(g: np.ndarray, sigmas: tuple[float, ...]) -> np.ndarray:
    """float32 H x W max over scales of the scale-normalised determinant of Hessian (>= 0)."""
    out = np.zeros(g.shape, dtype=np.float32)
    L, prev = g.astype(np.float32), 0.0
    for s in sorted(sigmas):
        inc = float(np.sqrt(max(s * s - prev * prev, 0.0)))
        if inc > 0:
            L = gaussian_filter(L, inc, mode="nearest")
        prev = s
        P = np.pad(L, 1, mode="edge")
        lxx = P[1:-1, 2:] - 2 * L + P[1:-1, :-2]
        lyy = P[2:, 1:-1] - 2 * L + P[:-2, 1:-1]
        lxy = (P[2:, 2:] - P[2:, :-2] - P[:-2, 2:] + P[:-2, :-2]) * 0.25
        np.maximum(out, (s**4) * (lxx * lyy - lxy * lxy), out=out)
    return out


@register("keypoints2d")
def keypoints2d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W multi-scale determinant-of-Hessian blob response of the grey image."""
    r = doh_response(grey(ctx), tuple(ctx.params.keypoints2d_sigmas))
    return to_uint16_scaled(r, ctx.params.keypoints2d_scale)


def _shift(a: np.ndarray, dy: int, dx: int, fill: float) -> np.ndarray:
    """a shifted so out[y, x] = a[y + dy, x + dx], `fill` outside."""
    out = np.full_like(a, fill)
    h, w = a.shape[:2]
    out[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)] = a[max(0, dy):h - max(0, -dy),
                                                                    max(0, dx):w - max(0, -dx)]
    return out


def _blur(x: np.ndarray, radius_px: int) -> np.ndarray:
    """Approximately Gaussian blur with sigma ~ radius/2: three box passes of width ~radius (O(1) per pixel)."""
    size = max(1, int(radius_px)) | 1
    for _ in range(3):
        x = uniform_filter(x, size, mode="constant")
    return x


def narf_interest(ctx: ViewContext) -> np.ndarray:
    """float32 H x W NARF-like interest in [0, 1] (module docstring), 0 off valid depth."""
    v = valid(ctx)
    if not v.any():
        return np.zeros(v.shape, dtype=np.float32)
    f = float(ctx.geometry.K[0, 0])
    d = ray_dirs_cam(ctx)
    z = np.where(v, depth_m(ctx), 0.0).astype(np.float32)
    rng = np.where(v, z / d[..., 2], np.inf).astype(np.float32)  # euclidean range, inf = none
    P = d * np.where(v, rng, 0.0)[..., None]
    # 2. foreground borders: the neighbour is missing or much farther.
    border = np.zeros(v.shape, dtype=bool)
    thresh = BORDER_FOOTPRINTS * np.where(v, rng, 0.0) / f
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        rq = _shift(rng, dy, dx, np.inf)
        with np.errstate(invalid="ignore"):  # inf - inf off the surface; masked by v anyway
            border |= v & (rq - rng > thresh)
    # 1. normals from central differences where both neighbours on each axis are valid surface.
    smooth = v & ~border
    du = _shift(P, 0, 1, 0.0) - _shift(P, 0, -1, 0.0)
    dv = _shift(P, 1, 0, 0.0) - _shift(P, -1, 0, 0.0)
    ok = smooth & _shift(smooth, 0, 1, False) & _shift(smooth, 0, -1, False) \
        & _shift(smooth, 1, 0, False) & _shift(smooth, -1, 0, False)
    n = np.cross(du, dv)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n = np.where((np.einsum("hwc,hwc->hw", n, d) > 0)[..., None], -n, n)
    w = ok.astype(np.float32)
    n = n * w[..., None]
    # 3./4. per-pixel scale from the metric support size, blended linearly in log2 between the two nearest
    # scales so the image has no seams where the depth crosses a scale boundary.
    support_px = f * ctx.params.keypoints3d_support_m / np.where(v, z, np.inf)
    kf = np.clip(np.log2(np.maximum(support_px, 1e-6)), 0, len(KP3D_SCALES_PX) - 1)
    k0 = np.floor(kf).astype(np.int64)
    k1 = np.minimum(k0 + 1, len(KP3D_SCALES_PX) - 1)
    t = (kf - k0).astype(np.float32)
    used = np.unique(np.concatenate([k0[v], k1[v]]))

    def blend(out: np.ndarray, ki: int, value: np.ndarray) -> None:
        out += np.where(k0 == ki, (1 - t) * value, 0.0) + np.where(k1 == ki, t * value, 0.0)

    change = np.zeros(v.shape, dtype=np.float32)
    for ki in used:
        radius = KP3D_SCALES_PX[ki]
        cnt = _blur(w, radius)
        m = np.stack([_blur(n[..., c], radius) for c in range(3)], axis=-1)
        m /= np.maximum(cnt, 1e-6)[..., None]
        c = np.sqrt(np.clip(1.0 - np.einsum("hwc,hwc->hw", m, m), 0.0, 1.0))
        blend(change, int(ki), np.where(cnt > 1e-6, c, 0.0).astype(np.float32))
    change[border] = 1.0
    change[~v] = 0.0
    gx, gy = sobel(change, axis=1, mode="nearest"), sobel(change, axis=0, mode="nearest")
    jxx, jyy, jxy = gx * gx, gy * gy, gx * gy
    iso = np.zeros(v.shape, dtype=np.float32)
    for ki in used:
        a, b, c = (_blur(x, KP3D_SCALES_PX[ki]) for x in (jxx, jyy, jxy))
        tr = a + b
        disc = np.sqrt(np.maximum((a - b) ** 2 / 4 + c * c, 0.0))
        lo, hi = tr / 2 - disc, tr / 2 + disc
        val = np.where(tr > 1e-6, 2 * np.maximum(lo, 0.0) / np.maximum(lo + hi, 1e-12), 0.0)
        blend(iso, int(ki), val.astype(np.float32))
    iso[~v] = 0.0
    return np.clip(change * iso, 0.0, 1.0).astype(np.float32)


@register("keypoints3d")
def keypoints3d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W NARF-like 3D interest from the range image: round(interest * 65535)."""
    return to_uint16_scaled(ctx.memo("narf_interest", lambda: narf_interest(ctx)), 65535.0)
