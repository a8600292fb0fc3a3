"""rgb_refocus: the view photographed through a thin lens focused at a drawn distance (the Omnidata paper's 3D
refocusing, with the circle of confusion of a real lens instead of a blur proportional to depth).

Thin lens of focal length f (from the view's fov and the sensor width), aperture diameter A = f / N, focused
at distance S (a drawn quantile of the view's depths): a point at depth d (along the optical axis) images to a
disc of diameter c = A |d - S| / d * f / (S - f) on the sensor, c / sensor_width * W pixels. Pixels with no
surface are at infinity (c = A f / (S - f)). Each pixel takes the image blurred by a disc of its own radius
(`gather`: radii quantised to half a pixel up to 4 px, whole pixels up to 16, then 2 px; at most
refocus_max_coc_px), computed in linear light. A pixel at the focus distance keeps its colour exactly. Not
modelled: a sharp foreground's light spilling over a blurred background (occlusion at depth edges).
"""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.cues.augment_params import draw, linear_to_srgb, srgb_to_linear
from services.worker.cues.common import depth_m, valid
from services.worker.cues.registry import cue_array, register

SUPERSAMPLE = 8  # disc kernels: coverage of each pixel by the disc, from 8 x 8 samples


def coc_radius_px(depth: np.ndarray, *, focus_m: float, f_number: float, focal_mm: float, sensor_mm: float,
                  width_px: int) -> np.ndarray:
    """Radius in pixels of the circle of confusion of points at `depth` metres (inf: at infinity)."""
    f = focal_mm / 1000.0
    aperture = f / f_number
    s = max(focus_m, f * 1.0001)  # focused nearer than f: nothing is sharp; keep the formula finite
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.isfinite(depth), np.abs(depth - s) / depth, 1.0)
    diameter_m = aperture * ratio * f / (s - f)
    return (0.5 * diameter_m / (sensor_mm / 1000.0) * width_px).astype(np.float64)


def quantise_radius(r: np.ndarray) -> np.ndarray:
    """Blur levels: half pixels up to 4 px, whole pixels up to 16, then 2 px steps (0 = sharp)."""
    r = np.asarray(r, dtype=np.float64)
    return np.where(r < 4, np.round(r * 2) / 2, np.where(r < 16, np.round(r), np.round(r / 2) * 2))


def disc_kernel(radius: float) -> np.ndarray:
    """A normalised disc of `radius` pixels, each weight the share of its pixel the disc covers."""
    half = int(np.ceil(radius))
    offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    grid = np.arange(-half, half + 1, dtype=np.float64)
    ys = (grid[:, None] + offsets[None, :]).reshape(-1)
    inside = (ys[:, None] ** 2 + ys[None, :] ** 2) <= radius**2
    cover = inside.reshape(len(grid), SUPERSAMPLE, len(grid), SUPERSAMPLE).mean(axis=(1, 3))
    return cover / cover.sum()


def disc_blur(image: np.ndarray, radius: float) -> np.ndarray:
    """H x W x C image convolved with disc_kernel(radius), edges extended."""
    if radius < 0.25:
        return image
    # imported here: scipy.signal brings scipy.stats (~0.6 CPU-s), which every worker paid at start-up for a
    # cue that is off by default
    from scipy.signal import fftconvolve

    kernel = disc_kernel(radius)
    pad = kernel.shape[0] // 2
    padded = np.pad(image, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    return np.stack(
        [fftconvolve(padded[..., c], kernel, mode="valid") for c in range(image.shape[2])], axis=-1
    )


def refocus(linear: np.ndarray, radius_px: np.ndarray) -> np.ndarray:
    """Each pixel of the linear H x W x 3 image blurred by a disc of its own (quantised) radius."""
    levels = quantise_radius(radius_px)
    out = np.array(linear, dtype=np.float64)
    for level in np.unique(levels):
        if level <= 0:
            continue
        mask = levels == level
        out[mask] = disc_blur(np.asarray(linear, dtype=np.float64), float(level))[mask]
    return out


@register("rgb_refocus")
def rgb_refocus(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3 sRGB: rgb refocused at the view's drawn focus distance and f-number."""
    p = draw(ctx)["rgb_refocus"]
    depth = np.where(valid(ctx), depth_m(ctx), np.inf)
    radius = coc_radius_px(
        depth, focus_m=p["focus_distance_m"], f_number=p["f_number"], focal_mm=p["focal_length_mm"],
        sensor_mm=p["sensor_width_mm"], width_px=ctx.resolution,
    )
    radius = np.minimum(radius, p["max_coc_px"])
    return linear_to_srgb(refocus(srgb_to_linear(cue_array(ctx, "rgb")), radius))
