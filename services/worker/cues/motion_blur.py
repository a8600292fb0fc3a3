"""rgb_motion_blur: the camera translates by t (drawn, metres, camera axes) while the shutter is open.

At time s in [-1/2, 1/2] of the exposure the camera centre sits at s t. A pixel q with depth Z sees the point
X = Z K^-1 (q + 1/2); at time s that point projects to p_s = K (X - s t) / (X - s t)_z, so the image moves by
d_s(q) = p_s - q: a near point moves more than a far one, a sideways move (x, y) smears along the image axes
and a forward move (z) smears radially from the principal point. The blurred image is the mean over the
exposure of the image at each instant, I_s(q) = I(q - d_s(q)) (the displacement at q standing for that of the
point that lands there: exact where depth is locally constant), with as many instants as make consecutive ones
at most 1 px apart (at most motion_max_samples), in linear light. Points at infinity (no surface) do not move.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import map_coordinates

from services.worker.context import ViewContext
from services.worker.cues.augment_params import draw, focal_px, linear_to_srgb, srgb_to_linear
from services.worker.cues.common import depth_m, valid
from services.worker.cues.registry import cue_array, register

NEAREST_Z_M = 1e-3  # a point the camera would reach during the exposure stays where it is


def displacement(
    depth: np.ndarray, translation: np.ndarray, focal: float, s: float
) -> tuple[np.ndarray, np.ndarray]:
    """(du, dv) in pixels of each pixel's point at time s (0 where the depth is infinite)."""
    h, w = depth.shape
    cx, cy = 0.5 * w, 0.5 * h
    u = np.arange(w, dtype=np.float64)[None, :] + 0.5 - cx
    v = np.arange(h, dtype=np.float64)[:, None] + 0.5 - cy
    finite = np.isfinite(depth)
    z = np.where(finite, depth, 1.0)
    x, y = u * z / focal, v * z / focal
    tx, ty, tz = (s * float(c) for c in translation)
    zs = z - tz
    ok = finite & (zs > NEAREST_Z_M)
    with np.errstate(divide="ignore", invalid="ignore"):
        du = np.where(ok, focal * (x - tx) / zs - u, 0.0)
        dv = np.where(ok, focal * (y - ty) / zs - v, 0.0)
    return du, dv


def motion_blur(linear: np.ndarray, depth: np.ndarray, translation: np.ndarray, focal: float,
                max_samples: int) -> tuple[np.ndarray, int]:
    """(blurred linear H x W x 3 image, instants averaged)."""
    du, dv = displacement(depth, translation, focal, 0.5)
    extent = 2.0 * float(np.max(np.hypot(du, dv), initial=0.0))  # pixels travelled over the whole exposure
    samples = int(min(max(math.ceil(extent) + 1, 2), max_samples))
    h, w = depth.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.zeros_like(linear, dtype=np.float64)
    for s in np.linspace(-0.5, 0.5, samples):
        du, dv = displacement(depth, translation, focal, float(s))
        coords = np.stack([rows - dv, cols - du])
        for c in range(linear.shape[2]):
            out[..., c] += map_coordinates(linear[..., c], coords, order=1, mode="nearest")
    return out / samples, samples


@register("rgb_motion_blur")
def rgb_motion_blur(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3 sRGB: rgb blurred by the view's drawn camera translation during the exposure."""
    p = draw(ctx)["rgb_motion_blur"]
    depth = np.where(valid(ctx), depth_m(ctx), np.inf)
    blurred, _ = motion_blur(srgb_to_linear(cue_array(ctx, "rgb")), depth, np.asarray(p["translation_m"]),
                             focal_px(ctx), int(p["max_samples"]))
    return linear_to_srgb(blurred)
