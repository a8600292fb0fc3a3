"""Semantic cues of labelled spaces: per-face class and instance ids rendered through AOVs.

Ids are written as the space gives them; negative ids (a scan's "unlabelled", e.g. Replica's -1) become 0, and
where nothing is seen both are 0 (tell "no surface" from a real id 0 with mask_valid). An id that the file
cannot hold (class > 255, instance > 65535) is an error naming the id, never silently wrapped.
Panoptic packing (Omnidata's): R = class, G * 256 + B = instance.
"""

from __future__ import annotations

import numpy as np

from services.worker.context import SemanticsUnavailableError, ViewContext
from services.worker.cues.common import hit
from services.worker.cues.registry import cue_array, register


def _labels(ctx: ViewContext, cue: str) -> tuple[np.ndarray, np.ndarray]:
    p = ctx.passes
    if p.face_class is None or p.face_instance is None:
        raise SemanticsUnavailableError(
            f"cue {cue!r} needs semantic labels, and the space has none (unlabelled scan): "
            "only labelled spaces (per-face class/instance ids) support segment_semantic, segment_instance "
            "and segment_panoptic"
        )
    h = hit(ctx)
    cls = np.where(h, np.maximum(p.face_class, 0), 0)
    inst = np.where(h, np.maximum(p.face_instance, 0), 0)
    for name, ids, limit in (("class", cls, 255), ("instance", inst, 65535)):
        if ids.size and ids.max() > limit:
            raise ValueError(
                f"cue {cue!r}: {name} id {int(ids.max())} in view exceeds {limit}, the largest the "
                f"{'8' if limit == 255 else '16'}-bit encoding holds"
            )
    return cls, inst


@register("segment_semantic", passes={"labels"})
def segment_semantic(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W class id per pixel (0 where nothing is seen)."""
    cls, _ = _labels(ctx, "segment_semantic")
    return cls.astype(np.uint8)


@register("segment_instance", passes={"labels"})
def segment_instance(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W instance id per pixel (0 where nothing is seen)."""
    _, inst = _labels(ctx, "segment_instance")
    return inst.astype(np.uint16)


def pack_panoptic(cls: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """uint8 H x W x 3 with R = class, G = instance // 256, B = instance % 256."""
    inst = inst.astype(np.uint32)
    return np.stack(
        [cls.astype(np.uint8), (inst >> 8).astype(np.uint8), (inst & 0xFF).astype(np.uint8)], axis=-1
    )


def unpack_panoptic(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of pack_panoptic: (class uint8 H x W, instance uint16 H x W)."""
    rgb = np.asarray(rgb)
    return rgb[..., 0].astype(np.uint8), (rgb[..., 1].astype(np.uint16) << 8) | rgb[..., 2].astype(np.uint16)


@register("segment_panoptic")
def segment_panoptic(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3 panoptic packing of segment_semantic and segment_instance."""
    return pack_panoptic(cue_array(ctx, "segment_semantic"), cue_array(ctx, "segment_instance"))
