"""Refining a capture's colour camera by maximising the alignment score (cameras.capture_refine).

Coordinate ascent over one correction shared by all frames (services.core.ingest.capture.calibration): focal
scale, principal point, and the colour camera's offset across the image plane (x, y; along the axis barely
moves edges), scored as the median alignment of up to REFINE_FRAMES frames spread over the capture at
REFINE_PX pixels. Steps halve when no move helps. The record says where it started, where it ended and what
was changed.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from services.core.domain.capture_records import RefinedCamera
from services.core.ingest.capture.calibration import ColourCorrection
from services.core.ingest.capture.model import Capture
from services.core.ingest.capture.photos import Photo
from services.scheduler.planning.alignment import alignment_score, scoring_photo
from services.scheduler.planning.visibility import MeshQueries

REFINE_FRAMES = 12
REFINE_PX = 128
# (field, first step): focal scale, principal point px, offset metres
STEPS = (("focal_scale", 0.04), ("dcx", 8.0), ("dcy", 8.0), ("ox", 0.02), ("oy", 0.02))
HALVINGS = 3
FOCAL_MARGIN = 1.25  # photos are decoded for a focal length this much above the start's: the search scales it


def _score(q: MeshQueries, photos: list[Photo], capture: Capture, picks: list[int],
           c: ColourCorrection) -> float:
    scores = []
    for photo, i in zip(photos, picks, strict=True):
        f = c.frame(capture.frames[i])
        s = alignment_score(q, photo, f, f.world_to_camera, f.inscribed_fov(), REFINE_PX)
        scores.append(s if s is not None else 0.0)
    return float(np.median(scores))


def _moved(c: ColourCorrection, name: str, delta: float) -> ColourCorrection:
    if name in ("ox", "oy"):
        off = list(c.offset_m)
        off["xy".index(name[1])] += delta
        return dataclasses.replace(c, offset_m=(off[0], off[1], off[2]))
    return dataclasses.replace(c, **{name: getattr(c, name) + delta})


def refine_colour_camera(q: MeshQueries, capture: Capture, frames: int = REFINE_FRAMES,
                         halvings: int = HALVINGS) -> tuple[ColourCorrection, RefinedCamera]:
    """The correction that maximises the median alignment score, and the record of the search."""
    picks = sorted(
        {int(i) for i in np.linspace(0, len(capture.frames) - 1, min(frames, len(capture.frames)))}
    )
    photos = [scoring_photo(str(capture.image_path(capture.frames[i])), capture.frames[i],
                            capture.frames[i].inscribed_fov(), int(REFINE_PX * FOCAL_MARGIN)) for i in picks]
    best = ColourCorrection()
    best_score = start = _score(q, photos, capture, picks, best)
    evaluations = 1
    for level in range(halvings + 1):
        improved = True
        while improved:
            improved = False
            for name, step in STEPS:
                for sign in (1.0, -1.0):
                    cand = _moved(best, name, sign * step / 2**level)
                    s = _score(q, photos, capture, picks, cand)
                    evaluations += 1
                    if s > best_score + 1e-4:
                        best, best_score, improved = cand, s, True
                        break
    record: RefinedCamera = {
        "correction": best.as_dict(), "score_before": start, "score_after": best_score,
        "frames_scored": len(picks), "evaluations": evaluations,
        "refined": "focal length scale, principal point, colour camera offset in x and y (shared by "
        "all frames)",
    }
    return best, record
