"""The up candidates of a scan and what a file says about its up: the facts `gravity` measures along each
candidate, the evidence terms `up_evidence` scores them with, and the file's own frame.

Frames and units: the source frame and the file's units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.core.domain.frame_records import UpCandidateRecord


@dataclass(frozen=True)
class FileFrame:
    """What a file says about its up, before any geometry: the format's up axis (source frame) and whether the
    format's specification fixes it (glTF) or it is a habit (PLY, OBJ)."""

    axis: np.ndarray
    binding: bool = False
    cloud: bool = False  # a point cloud meshed on ingest: its sides were estimated (up_evidence's `mirror`)
    camera: bool = False  # a cloud stored in an OpenCV camera's frame (`camera_frame`): up has a share of -Y
    origin_camera: bool = False  # its origin is its camera's place, turned or not (`origin_is_camera`)


# a candidate whose lower half faces it over this share of its cross-section could be a floor (a strip: a
# corridor's floor seen from a level depth camera covers 7-8 % of its frustum's; 0.1 left a levelled export of
# one refused, and no outcome of bench/ingest/ingest.py or of the other real rooms moved)
PLAUSIBLE_FLOOR_FRACTION = 0.05


@dataclass(frozen=True)
class CandidateFacts:
    """What gravity measured along one candidate direction (source frame, source units)."""

    up: np.ndarray
    area_score: float  # floor area + furniture surplus
    floor_area: float
    floor_fraction: float
    height: float  # extent along up
    cross_section: float  # convex cross-section area across up
    ceiling_fraction: float  # area facing down in the top half / cross-section
    mid_up: float  # area facing up between the end bands (furniture tops)
    mid_down: float  # area facing down between the end bands
    # the smaller share of the surface on either side of the source origin's height along up: where the origin
    # is the capture's camera, whether it saw the scan both above and below its own height
    origin_split: float = 0.0
    # the source origin's height above the floor along up: where the origin is the capture's camera, how high
    # it was held over the floor this candidate sees
    origin_height: float = 0.0
    # the sine of the elevation along up of the mean direction from the source origin to the surface: where
    # the origin is the capture's camera, how far up (> 0) or down (< 0) it looked
    origin_gaze: float = 0.0

    @property
    def plausible_floor(self) -> bool:
        """True when enough of the cross-section faces this up at the low end to be a floor."""
        return self.floor_fraction >= PLAUSIBLE_FLOOR_FRACTION


@dataclass(frozen=True)
class ScoredCandidate:
    """A candidate and its evidence terms (log-odds)."""

    facts: CandidateFacts
    terms: dict[str, float] = field(default_factory=dict)

    @property
    def up(self) -> np.ndarray:
        """The candidate up direction, source frame."""
        return self.facts.up

    @property
    def score(self) -> float:
        """The sum of the evidence terms."""
        return float(sum(self.terms.values()))

    def record(self, unit_scale: float | None = None) -> UpCandidateRecord:
        """JSON-ready: direction, floor area and storey height (metres when `unit_scale` is known), terms."""
        f = self.facts
        out: UpCandidateRecord = {
            "up": [round(float(x), 6) for x in f.up],
            "score": round(self.score, 3),
            "evidence": {k: round(v, 3) for k, v in self.terms.items()},
            "floor_fraction": round(f.floor_fraction, 4),
        }
        if unit_scale is not None:
            out["floor_area_m2"] = round(f.floor_area * unit_scale**2, 3)
            out["storey_height_m"] = round(f.height * unit_scale, 3)
        else:
            out["floor_area_units2"] = round(f.floor_area, 6)
            out["storey_height_units"] = round(f.height, 6)
        return out
