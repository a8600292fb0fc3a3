"""Cues of views whose rgb comes from photos (posed captures)."""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.cues.registry import register


@register("mask_photo")
def mask_photo(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W: 255 where the rgb is a photograph's (the photo covers the pixel), else 0."""
    covered = ctx.passes.photo_coverage
    if covered is None:
        raise RuntimeError("mask_photo needs a view whose rgb came from photos (cameras.mode capture or "
                           "views.rgb_source photos)")
    return np.where(covered, 255, 0).astype(np.uint8)
