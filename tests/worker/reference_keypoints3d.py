"""NARF-like interest (keypoints3d) as implemented before issue 10 (every blur at full resolution), kept only as
the reference of the equivalence tests (test_cue_equivalence.py). Not used by the service.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import sobel, uniform_filter

from services.worker.context import ViewContext
from services.worker.cues.common import depth_m, ray_dirs_cam, valid
from services.worker.cues.keypoints import BORDER_FOOTPRINTS, KP3D_SCALES_PX, _shift


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
