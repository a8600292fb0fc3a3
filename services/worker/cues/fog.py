"""rgb_fog: the view seen through homogeneous fog (Koschmieder's model), in linear light.

I = J t + A (1 - t) with transmittance t = exp(-beta d), d the distance from the camera centre along the ray
(metres), beta the drawn extinction coefficient (1/m) and A the drawn grey atmospheric light. Where no surface
is seen, d is infinite: t = 0, the fog's own colour.
"""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.cues.augment_params import draw, linear_to_srgb, srgb_to_linear
from services.worker.cues.common import euclidean_m, valid
from services.worker.cues.registry import cue_array, register


def transmittance(distance_m: np.ndarray, beta_per_m: float) -> np.ndarray:
    """exp(-beta d) per pixel (0 where the distance is infinite)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.where(
            np.isfinite(distance_m), np.exp(-beta_per_m * np.nan_to_num(distance_m, posinf=0.0)), 0.0
        )


def fog(linear: np.ndarray, distance_m: np.ndarray, *, beta_per_m: float, airlight: float) -> np.ndarray:
    """Linear H x W x 3 image seen through fog."""
    t = transmittance(distance_m, beta_per_m)[..., None]
    return linear * t + airlight * (1.0 - t)


@register("rgb_fog")
def rgb_fog(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3 sRGB: rgb through fog of the view's drawn density and colour."""
    p = draw(ctx)["rgb_fog"]
    distance = np.where(valid(ctx), euclidean_m(ctx), np.inf)
    return linear_to_srgb(fog(srgb_to_linear(cue_array(ctx, "rgb")), distance, beta_per_m=p["beta_per_m"],
                              airlight=p["airlight"]))
