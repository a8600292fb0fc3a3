"""Edge cues: texture edges from the colour image, occlusion edges from the depth image (16-bit PNGs).

Both store round(response * edge_scale) clipped to 0..65535, where response is scipy's unnormalised 3x3 Sobel
magnitude (a unit step gives 4): for texture edges of a [0, 1] grey image, for occlusion edges of
sqrt(metres).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from services.worker.context import ViewContext
from services.worker.cues.common import depth_m, gaussian_blur, grey, sobel_magnitude, to_uint16_scaled, valid
from services.worker.cues.registry import register


@register("edge_texture")
def edge_texture(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W: Sobel magnitude of the Gaussian-blurred (edge_texture_sigma px) grey rgb, whole image."""
    g = grey(ctx)
    s = ctx.params.edge_texture_sigma
    blurred = gaussian_blur(g, s) if s > 0 else g
    return to_uint16_scaled(sobel_magnitude(blurred), ctx.params.edge_scale)


def occlusion_response(ctx: ViewContext) -> np.ndarray:
    """float32 H x W Sobel magnitude of sqrt(depth in metres), blurred by edge_occlusion_sigma px, 0 off valid
    depth.

    Pixels without valid depth count as max_depth_m (the background is 'far', like 65535 in the original depth
    PNGs), so silhouettes against the background are occlusion edges.
    """

    def compute() -> np.ndarray:
        v = valid(ctx)
        s = _sqrt_depth(v, depth_m(ctx), np.float32(ctx.params.max_depth_m))
        sig = ctx.params.edge_occlusion_sigma
        if sig > 0:
            s = gaussian_blur(s, sig)
        return sobel_magnitude(s, mask=v)

    return ctx.memo("occlusion_response", compute)


@njit(cache=True, nogil=True, error_model="numpy")
def _sqrt_depth(v: np.ndarray, depth: np.ndarray, far: np.float32) -> np.ndarray:
    """float32 sqrt of the depth where valid, of `far` elsewhere (numpy's where, cast and sqrt in one
    pass)."""
    h, w = v.shape
    out = np.empty((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            out[y, x] = np.sqrt(depth[y, x] if v[y, x] else far)
    return out


@register("edge_occlusion")
def edge_occlusion(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W: round(edge_scale * occlusion_response), masked to valid depth."""
    return to_uint16_scaled(occlusion_response(ctx), ctx.params.edge_scale)
