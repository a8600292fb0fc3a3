"""Cue implementations, one module per family, collected into one registry, so the executor
looks cues up by name and a new cue touches one family module.

Adding a cue: a catalog entry in services/core/domain/cues.py, an `@register("name")` function in a family
module below, and (for a new family) one import line here.
"""

from services.worker.cues import (  # noqa: F401  (imported for their @register side effect)
    augment_params,
    basic,
    edges,
    flash,
    fog,
    keypoints,
    motion_blur,
    photo,
    plan_cues,
    refocus,
    segmentation,
    semantic,
)
from services.worker.cues.encoding import encode
from services.worker.cues.registry import REGISTRY, CueImpl, get_impl, register

__all__ = ["REGISTRY", "CueImpl", "encode", "get_impl", "register"]
