"""rgb_flash: the scan relit by a flash at the camera, on top of a share of its own (baked) light.

I = J (a + P cos / d^2), in linear light: J the scan's colour, a the drawn ambient share, P the drawn flash
power (m^2), cos the cosine between the surface normal and the direction to the camera (reshading's shading,
without its albedo) and d the distance to the camera centre. Where no surface is seen only the ambient share
remains. Values above 1 clip (an over-exposed flash).
"""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.cues.augment_params import draw, linear_to_srgb, srgb_to_linear
from services.worker.cues.basic import reshading_intensity
from services.worker.cues.common import euclidean_m, valid
from services.worker.cues.registry import cue_array, register


def flash(linear: np.ndarray, cosine: np.ndarray, distance_m: np.ndarray, *, ambient: float,
          power_m2: float) -> np.ndarray:
    """Linear H x W x 3 image under the flash."""
    with np.errstate(divide="ignore", invalid="ignore"):
        lit = np.where(np.isfinite(distance_m) & (distance_m > 0), power_m2 * cosine / distance_m**2, 0.0)
    return linear * (ambient + lit)[..., None]


@register("rgb_flash")
def rgb_flash(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3 sRGB: rgb lit by the view's drawn flash."""
    p = draw(ctx)["rgb_flash"]
    # reshading (a declared input, so the normal pass is rendered) is albedo x this cosine; the float is exact
    cosine = reshading_intensity(ctx) / ctx.params.reshading_albedo
    distance = np.where(valid(ctx), euclidean_m(ctx), np.inf)
    return linear_to_srgb(flash(srgb_to_linear(cue_array(ctx, "rgb")), cosine, distance, ambient=p["ambient"],
                                power_m2=p["power_m2"]))
