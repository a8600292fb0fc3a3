"""Units of a scan: the storey rule and the objects' plausibility check (`choose_unit_scale`), and for rooms
more evidence than the storey height, with a refusal when the units stay ambiguous.

Frames and units: the mesh in its source frame and the file's units; `up` is a unit vector in that frame.
A unit is a candidate when it puts the scan's height (floor to top along up) in a room's range: 1.8-6 m
with a ceiling seen (a storey), 0.8-6 m without one (a partial scan stops wherever the capture did: a floor
around a sofa and a coffee table is 1.1 m tall). Only centimetres and inches (a factor 2.54) can both fit:
every other pair of units is more than 6 / 0.8 apart. Each candidate is scored with log-odds terms:

- `storey`: -0.5 above 3.5 m (tall rooms are rare), else 0.
- `camera`: RGB-D reconstructions are stored in their first camera's frame, so the origin is where a
  person held the camera: when it lies over the scan, 0.75-2.0 m above the floor (a person's hands) scores
  +1, the rest of 0.3-2.2 m (a robot's, a camera held high) +0.5 (an origin elsewhere says nothing:
  exporters put it anywhere).
- `furniture`: seats, tables and counters are what a scan sees from above, at 0.35-1.0 m. When the
  up-facing surfaces between floor and top cover at least 5 % of the floor, the share of their area at
  those heights scores -1 below a quarter, and +1 from half of it up where read 2.54 times off less than a
  quarter is (one unit puts a room's seats and tables there; a unit 2.54 times off puts them at 0.9-2.5 m or
  0.15-0.4 m, and counters at 0.9-1.0 m at seat height).
- `spacing`: RGB-D fusions are meshed at 0.5-6 cm (TSDF voxels, Poisson depth): a median triangle edge
  in that range scores +0.5 (a dense scan whose edges would be 10 cm in one unit and 4 cm in the other).

The winner must beat every other plausible unit by `REFUSE_MARGIN`; otherwise the units are ambiguous
and loading refuses them (`UnitsAmbiguous`) unless guesses are accepted, naming each candidate with what
it would make the scan (storey and extent in metres) and `--unit-scale`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from services.core.domain.frame_records import UnitCandidateRecord, UnitsRecord

# storey height (floor to top of the scan) that a room must have once scaled, metres
STOREY_RANGE_M = (1.8, 6.0)
# tried only when no unit fits STOREY_RANGE_M: a partial scan without its ceiling (a few seconds of RGB-D
# capture reach 1.3-2 m above the floor)
PARTIAL_STOREY_RANGE_M = (1.2, 6.0)
# tried in this order: the first that puts the storey height in range wins (cm before inches: the
# ranges overlap for 180-236 units, and centimetre exports are far more common)
UNIT_CANDIDATES: tuple[tuple[str, float], ...] = (
    ("metres", 1.0), ("centimetres", 0.01), ("millimetres", 0.001), ("inches", 0.0254),
)
OBJECT_EXTENT_RANGE_M = (0.001, 50.0)


@dataclass(frozen=True)
class UnitChoice:
    """Metres per source unit and why."""

    scale: float
    unit: str  # metres | centimetres | millimetres | inches | given | source_to_world
    reason: str
    ambiguous: bool = False  # another unit is about as plausible (`decide_units`)
    candidates: tuple[UnitCandidateRecord, ...] = ()  # the plausible units, best first, when more than one

    def record(self) -> UnitsRecord:
        """JSON-ready summary."""
        out: UnitsRecord = {"unit_scale": self.scale, "unit": self.unit, "reason": self.reason}
        if self.candidates:
            out["ambiguous"] = self.ambiguous
            out["candidates"] = list(self.candidates)
        return out


class UnitError(ValueError):
    """No plausible unit; the message names `unit_scale`."""


def choose_unit_scale(storey_height: float | None, extent: float) -> UnitChoice:
    """Metres per source unit from a storey height (rooms) or a plausibility check (objects); source units."""
    if storey_height is not None and storey_height > 0:
        for lo, hi in (STOREY_RANGE_M, PARTIAL_STOREY_RANGE_M):
            for unit, scale in UNIT_CANDIDATES:
                if lo <= storey_height * scale <= hi:
                    return UnitChoice(scale, unit, f"storey height {storey_height:.4g} units is "
                                      f"{storey_height * scale:.3g} m in {unit} ({lo:g}-{hi:g} m)")
    omin, omax = OBJECT_EXTENT_RANGE_M
    if not omin <= extent <= omax:
        what = "a storey height" if storey_height else "an extent"
        raise UnitError(
            f"cannot tell the units: {what} of {storey_height or extent:.4g} units fits no storey in metres, "
            f"cm, mm or inches, and {extent:.4g} m across is implausible for an object "
            f"({omin * 1000:g} mm to {omax:g} m): set unit_scale (metres per source unit)"
        )
    if storey_height:
        return UnitChoice(1.0, "metres", f"storey height {storey_height:.4g} units fits no unit; "
                          f"kept metres ({extent:.4g} m across)")
    return UnitChoice(1.0, "metres", f"an object {extent:.4g} units across: kept metres")


UNIT_SCALES: tuple[tuple[str, float], ...] = (
    ("metres", 1.0), ("centimetres", 0.01), ("millimetres", 0.001), ("inches", 0.0254),
)
FULL_STOREY_M = (1.8, 6.0)  # a ceiling seen: floor to ceiling
PARTIAL_STOREY_M = (0.8, 6.0)  # no ceiling seen: floor to wherever the capture stopped
TYPICAL_TOP_M = 3.5
# where people hold a camera (the origins of the real hand-held RGB-D captures of bench/ingest/ingest_real.py
# lie 0.80-1.88 m above their floors), and where a camera may still be (a robot's: 0.47 m; one held high): a
# unit that puts it in the first beats one that puts it only in the second by half the camera term, so a
# robot's frame in centimetres, 1.2 m up in inches, is asked for, never read in inches
CAMERA_HELD_M = (0.75, 2.0)
CAMERA_POSSIBLE_M = (0.3, 2.2)
SUPPORT_HEIGHTS_M = (0.35, 1.0)  # seats 0.35-0.55, tables 0.6-0.8, counters 0.85-1.0
# share of the tops at those heights: below it -1; from the second +1 where the reading 2.54 times off holds
# less than the first (a unit tells itself apart only where the other puts few tops there: counters at
# 0.9-1.0 m are at seat height read 2.54 times off). Real rooms put 0.60-1.0 of their tops there in their
# unit, up to 0.56 read 2.54 times smaller and 0.13 (one frame of low tables 0.54) read 2.54 times larger
SUPPORT_SHARE = (0.25, 0.5)
FURNITURE_MIN_SHARE = 0.05
FUSION_EDGE_M = (0.005, 0.06)
REFUSE_MARGIN = 1.0
_UP_COS = float(np.cos(np.radians(15.0)))
_BAND = 0.10


@dataclass(frozen=True)
class UnitCandidate:
    """One unit that makes the storey plausible, its evidence terms and what it makes the scan."""

    unit: str
    scale: float  # metres per source unit
    storey_m: float
    extent_m: tuple[float, float, float]
    terms: dict[str, float] = field(default_factory=dict)

    @property
    def score(self) -> float:
        """The sum of the evidence terms."""
        return float(sum(self.terms.values()))

    def record(self) -> UnitCandidateRecord:
        """JSON-ready: unit, scale, storey and extent in metres, score and terms."""
        return {"unit": self.unit, "unit_scale": self.scale, "storey_height_m": round(self.storey_m, 3),
                "extent_m": [round(x, 2) for x in self.extent_m], "score": round(self.score, 3),
                "evidence": {k: round(v, 3) for k, v in self.terms.items()}}


@dataclass(frozen=True)
class ScanMeasures:
    """Unit-carrying measurements of a scan along an up direction (source units)."""

    storey: float  # floor (lowest point) to top along up
    extent: tuple[float, float, float]  # the scan's extents along its own principal axes, largest first
    ceiling_seen: bool
    origin_height: float | None  # the origin's height above the floor when it lies over the scan
    # the up-facing surfaces between the end bands: (heights above the floor, areas), when they cover
    # FURNITURE_MIN_SHARE of the floor
    tops: tuple[np.ndarray, np.ndarray] | None
    median_edge: float

    def support_share(self, scale: float) -> float | None:
        """The share of the tops' area at seat-to-counter heights with `scale` metres per unit."""
        if self.tops is None:
            return None
        h, a = self.tops[0] * scale, self.tops[1]
        return float(a[(h >= SUPPORT_HEIGHTS_M[0]) & (h <= SUPPORT_HEIGHTS_M[1])].sum() / a.sum())


def measure(mesh: trimesh.Trimesh, up: np.ndarray, ceiling_fraction: float | None = None) -> ScanMeasures:
    """The measurements the unit terms need, along `up` (source frame)."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    v = np.asarray(mesh.vertices)
    hv = v @ up
    lo, hi = float(hv.min()), float(hv.max())
    height = hi - lo
    h = np.asarray(mesh.triangles_center) @ up - lo
    c = np.asarray(mesh.face_normals) @ up
    areas = np.asarray(mesh.area_faces)
    floor = float(areas[(c > _UP_COS) & (h <= _BAND * height)].sum())
    tops = (c > _UP_COS) & (h > _BAND * height) & (h < (1 - _BAND) * height)
    found = (h[tops], areas[tops]) if floor > 0 and areas[tops].sum() >= FURNITURE_MIN_SHARE * floor else None
    if ceiling_fraction is None:
        down = float(areas[(c < -_UP_COS) & (h >= 0.5 * height)].sum())
        ceiling_fraction = down / floor if floor > 0 else float(down > 0)  # a ceiling over no floor: seen
    centre = v.mean(axis=0)
    flat = (v - centre) - np.outer((v - centre) @ up, up)
    _, _, axes = np.linalg.svd(flat[:: max(1, len(flat) // 20000)], full_matrices=False)
    spans = sorted((float(np.ptp(flat @ a)) for a in axes[:2]), reverse=True)
    # the origin counts as a camera when it lies over the scan (a camera looks at it from its edge, often
    # above its top): above the floor, within half a storey over the top, within the scan's span across
    origin_h = -lo
    across = float(np.linalg.norm(centre - (centre @ up) * up))
    inside = 0.0 < origin_h <= 1.5 * height and across <= spans[0]
    return ScanMeasures(height, (spans[0], spans[1], height), ceiling_fraction >= 0.3,
                        origin_h if inside else None, found, median_edge_length(mesh))


def median_edge_length(mesh: trimesh.Trimesh) -> float:
    """np.median(mesh.edges_unique_length), the same value, without trimesh's unique rows, which hash every
    edge (the 7-Scenes kitchen's 577k edges: 0.24 CPU-s against 0.05 here): each face edge as one int64 key,
    low vertex first, and np.unique of the keys. The lengths are trimesh's (v[low] - v[high], util.row_norm's
    arithmetic), and a median does not depend on their order."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    a, b = faces.ravel(), faces[:, [1, 2, 0]].ravel()  # each face's edges (0, 1), (1, 2), (2, 0)
    n = max(len(mesh.vertices), 1)
    keys = np.unique(np.minimum(a, b) * n + np.maximum(a, b))
    v = np.asarray(mesh.vertices)
    d = v[keys // n] - v[keys % n]
    return float(np.median(np.sqrt(np.dot(d**2, [1, 1, 1]))))  # trimesh.util.row_norm's expression


def _terms(m: ScanMeasures, scale: float) -> dict[str, float] | None:
    storey = m.storey * scale
    lo, hi = FULL_STOREY_M if m.ceiling_seen else PARTIAL_STOREY_M
    if not lo <= storey <= hi:
        return None
    terms = {"storey": -0.5 if storey > TYPICAL_TOP_M else 0.0}
    if m.origin_height is not None:
        cam = m.origin_height * scale
        held = CAMERA_HELD_M[0] <= cam <= CAMERA_HELD_M[1]
        terms["camera"] = 1.0 if held else 0.5 if CAMERA_POSSIBLE_M[0] <= cam <= CAMERA_POSSIBLE_M[1] else 0.0
    share = m.support_share(scale)
    if share is not None:
        rival = max(m.support_share(scale * 2.54) or 0.0, m.support_share(scale / 2.54) or 0.0)
        clear = share >= SUPPORT_SHARE[1] and rival < SUPPORT_SHARE[0]
        terms["furniture"] = 1.0 if clear else -1.0 if share < SUPPORT_SHARE[0] else 0.0
    edge = m.median_edge * scale
    terms["spacing"] = 0.5 if FUSION_EDGE_M[0] <= edge <= FUSION_EDGE_M[1] else 0.0
    return terms


@dataclass(frozen=True)
class UnitDecision:
    """The plausible units, best first, and whether the best clearly wins."""

    ranked: tuple[UnitCandidate, ...]

    @property
    def margin(self) -> float:
        """Best score minus the runner-up's (inf with one candidate)."""
        return float("inf") if len(self.ranked) < 2 else self.ranked[0].score - self.ranked[1].score

    @property
    def ambiguous(self) -> bool:
        """True when another plausible unit scores within `REFUSE_MARGIN` of the best."""
        return self.margin < REFUSE_MARGIN


def decide_units(m: ScanMeasures, disabled: tuple[str, ...] = ()) -> UnitDecision:
    """Score every unit that makes the storey plausible (empty when none does); `disabled`: terms left out
    (the bench's ablation)."""
    cands = []
    for unit, scale in UNIT_SCALES:
        terms = _terms(m, scale)
        if terms is not None:
            terms = {k: v for k, v in terms.items() if k not in disabled}
            extent = (m.extent[0] * scale, m.extent[1] * scale, m.extent[2] * scale)
            cands.append(UnitCandidate(unit, scale, m.storey * scale, extent, terms))
    order = {u: i for i, (u, _) in enumerate(UNIT_SCALES)}  # ties: the more common unit first
    return UnitDecision(tuple(sorted(cands, key=lambda c: (-c.score, order[c.unit]))))


def choose_units(mesh: trimesh.Trimesh, up: np.ndarray, storey_height: float | None) -> UnitChoice:
    """Metres per source unit of a scan levelled along `up`: the evidence above for rooms (`storey_height`
    set), gravity's plausibility check for objects; `ambiguous` when another unit is about as plausible."""
    extent = float(mesh.extents.max())
    if storey_height is None or storey_height <= 0:
        return choose_unit_scale(storey_height, extent)
    m = measure(mesh, up)
    d = decide_units(m)
    if not d.ranked:
        return choose_unit_scale(storey_height, extent)
    best = d.ranked[0]
    reason = f"storey height {m.storey:.4g} units is {best.storey_m:.3g} m in {best.unit}"
    if len(d.ranked) > 1:
        other = d.ranked[1]
        reason += (f" (over {other.unit}: {other.storey_m:.3g} m, by {d.margin:.2f}: "
                   + ", ".join(f"{k} {v:+g}" for k, v in best.terms.items() if v) + ")")
        return UnitChoice(best.scale, best.unit, reason, d.ambiguous, tuple(c.record() for c in d.ranked))
    return UnitChoice(best.scale, best.unit, reason)
