"""Where a point cloud's camera stood, as evidence for its up (`up_evidence`'s `camera_height` and
`camera_looked_down`): for a cloud whose origin is its camera's place (`camera_frame.origin_is_camera`),
how high over each candidate's floor that camera was held and how it looked at the scan.

Frames and units: the source frame and the file's units; heights are read in every unit that makes the scan
a room's height (`unit_evidence.PARTIAL_STOREY_M`).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from services.core.ingest.frame.candidates import CandidateFacts
from services.core.ingest.frame.unit_evidence import PARTIAL_STOREY_M, UNIT_SCALES

# a camera held higher than this above the floor it saw (a storey) was not held over that floor: the real
# clouds of bench/ingest/ingest_real.py whose origin is their camera hold it 0.3-2.7 m up
CAMERA_HEIGHT_MAX_M = 3.5
# this share of the surface at least on each side of the camera's height along a family: the camera looked
# across it, not only up at a ceiling or down at a floor
CAMERA_SPLIT_MIN = 0.05
# a camera that looked further down than this at a plane faced it (a wall), as a depth frame's view does
LOOKED_DOWN_MAX_SIN = float(np.sin(np.radians(50.0)))
# a camera whose mean gaze lies this close to a family's plane looked level across it (the corpus's level
# frames: 5 degrees down to 2 up on their points; their Poisson meshes' faces read up to 10 degrees off)
LEVEL_GAZE_SIN = float(np.sin(np.radians(15.0)))


def _room_units(f: CandidateFacts) -> list[float]:
    """The units (metres per unit) that make this candidate's height a room's."""
    lo, hi = PARTIAL_STOREY_M
    return [s for _, s in UNIT_SCALES if lo <= f.height * s <= hi]


def camera_too_high(f: CandidateFacts) -> bool:
    """True when the floor this candidate sees lies further below the camera at the origin than a storey in
    every unit that makes the scan a room's height: no one holds a camera there, so the floor is a ceiling
    seen from below."""
    units = _room_units(f)
    return f.plausible_floor and bool(units) and all(f.origin_height * s > CAMERA_HEIGHT_MAX_M for s in units)


def _pose(f: CandidateFacts) -> Literal["down", "across"] | None:
    """How the camera at the origin saw this candidate's floor: "down" when it saw nothing above its own
    height and looked down at what it saw (not straight at it: a wall it faced), "across" when it looked level
    across the family and saw it on both sides of its height, else None (no floor, a height no room has in
    any unit, or a floor too far below the camera for anyone to have held it there)."""
    if not f.plausible_floor or not _room_units(f) or camera_too_high(f):
        return None
    if f.origin_split < CAMERA_SPLIT_MIN:
        return "down" if -LOOKED_DOWN_MAX_SIN <= f.origin_gaze < 0.0 else None
    return "across" if abs(f.origin_gaze) <= LEVEL_GAZE_SIN else None


def camera_looked_down(candidates: list[CandidateFacts]) -> list[bool]:
    """Per candidate: the floor the camera at the origin looked down at from a hand's height (at most a
    storey over it in every unit that makes the scan a room's height), where the camera's place singles that
    candidate out: it looked down so at no other (a fragment cut to a cube shows walls as flat and furnished
    as its floor) nor level across another (a level frame, where a wall seen aslant lies wholly below it)."""
    poses = [_pose(f) for f in candidates]
    single = sum(p is not None for p in poses) == 1
    return [single and p == "down" and _held_by_hand(f) for f, p in zip(candidates, poses, strict=True)]


def _held_by_hand(f: CandidateFacts) -> bool:
    """True when the camera at the origin stood at most a storey over this candidate's floor in every unit
    that makes the scan a room's height."""
    units = _room_units(f)
    return bool(units) and all(f.origin_height * s <= CAMERA_HEIGHT_MAX_M for s in units)
