"""Evidence for each up candidate of a room scan, combined into one score and a calibrated confidence.

Frames and units: the source frame and the file's units (unknown here: every term is unit free).
A candidate is a plane-family direction `u` (one sign) proposed by `services.core.ingest.gravity`. Each term
below is a log-odds contribution; a candidate's score is their sum, and the decision compares the best
candidate with the best one that would level the scan differently (more than `DISTINCT_DEG` away):

- `floor_area`: the floor seen from above plus the furniture surplus (gravity's area score), as the log
  of its ratio to the best candidate's. Plane area alone is what fails on partial scans: a wall or a
  row of cabinet fronts can be as large as the visible floor.
- `furniture`: furniture tops face up and their undersides are rarely scanned, so the horizontal area at
  mid height faces down along the opposite of up: a penalty up to -1 for a candidate that sees mostly
  undersides (the ceiling taken as floor). No bonus: cabinet fronts do the same along a wall's normal.
- `extent`: rooms are wider than tall. Height along `u` over the square root of the cross-section
  across `u`, as the log of its ratio to the thinnest candidate's (a wall taken as floor turns the
  room's width into its "height").
- `storey`: whether the extent along `u` is a storey (2.2-3.5 m, or 1.2-3.5 m for a scan without a
  ceiling: partial scans rarely see it) in one of the units we accept; a penalty when it fits none.
- `capture_convention`: RGB-D reconstructions are stored in their first camera's OpenCV frame, so up
  lies within ~50 degrees of -Y; not for glTF, whose specification says +Y. Weak: a rotated file breaks it. Its weight is below `REFUSE_MARGIN`,
  so on its own it can turn a guess into a refusal but never into a confident answer.
- `capture_up`: the mean up vector of the capture's cameras (-Y of OpenCV cameras, averaged), when the
  caller has poses. Cameras are held upright, give or take their pitch: strong evidence.

The confidence is a logistic function of the margin (best score minus the runner-up's), calibrated on
the real and synthetic corpus of bench/ingest.py; below `REFUSE_MARGIN` the estimate is ambiguous and
planning does not go ahead on it unless the user accepted guesses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from services.core.ingest.frame_records import UpCandidateRecord

DISTINCT_DEG = 30.0  # candidates closer than this level the scan the same way
# score margin below which the estimate is ambiguous: on the bench corpus (real and synthetic, random
# rotations) no wrong winner scored more than 0.9 above its runner-up with these weights
REFUSE_MARGIN = 1.2
CONFIDENCE_SLOPE = 2.7  # logistic slope of P(right | margin), fitted on the bench corpus
CAPTURE_CONE_DEG = 50.0
POSE_CONE_DEG = 45.0
STOREY_M = (2.2, 3.5)
OPEN_STOREY_M = (1.2, 3.5)  # no ceiling scanned
UNIT_SCALES = (1.0, 0.01, 0.001, 0.0254)

WEIGHTS = {
    "floor_area": 1.5,
    "furniture": 2.0,
    "extent": 3.0,
    "storey": 0.5,
    "capture_convention": 0.8,
    "capture_up": 4.0,
}


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


@dataclass(frozen=True)
class UpDecision:
    """The scored candidates (best first), the runner-up that levels differently and how sure we are."""

    ranked: tuple[ScoredCandidate, ...]
    runner_up: ScoredCandidate | None
    margin: float  # best score - runner-up score (inf without a runner-up)
    confidence: float  # calibrated P(the best is right | margin), 0.5-1
    third: ScoredCandidate | None = None  # the best candidate levelling differently from both (shown on refusal)

    @property
    def shown(self) -> tuple[ScoredCandidate, ...]:
        """The candidates a person chooses from: best, runner-up and the third when there is one."""
        return tuple(c for c in (self.best, self.runner_up, self.third) if c is not None)

    @property
    def best(self) -> ScoredCandidate:
        """The winning candidate."""
        return self.ranked[0]

    @property
    def ambiguous(self) -> bool:
        """True when the winner does not clearly beat a candidate that levels the scan differently."""
        return self.margin < REFUSE_MARGIN


def _furniture_term(f: CandidateFacts) -> float:
    """+1 when mid-height horizontal surfaces all face up (tops seen, undersides not), -1 when all face down."""
    total = f.mid_up + f.mid_down
    return 0.0 if total <= 0 else (f.mid_up - f.mid_down) / total


def _storey_term(f: CandidateFacts) -> float:
    lo, hi = STOREY_M if f.ceiling_fraction >= 0.3 else OPEN_STOREY_M
    fits = any(lo <= f.height * s <= hi for s in UNIT_SCALES)
    return 0.0 if fits else -1.0


def evidence_terms(f: CandidateFacts, all_facts: list[CandidateFacts], capture_up: np.ndarray | None,
                   capture_convention: bool = True) -> dict[str, float]:
    """The log-odds terms of one candidate among all (see the module docstring)."""
    best_area = max(c.area_score for c in all_facts)
    ratios = [c.height / np.sqrt(c.cross_section) for c in all_facts if c.cross_section > 0 and c.height > 0]
    thinnest = min(ratios) if ratios else 1.0
    ratio = f.height / np.sqrt(f.cross_section) if f.cross_section > 0 and f.height > 0 else 10 * thinnest
    terms = {
        "floor_area": WEIGHTS["floor_area"] * float(np.log(max(f.area_score, 1e-12 * best_area) / best_area)),
        "furniture": WEIGHTS["furniture"] * min(0.0, _furniture_term(f)),
        "extent": -WEIGHTS["extent"] * float(np.log(ratio / thinnest)),
        "storey": WEIGHTS["storey"] * _storey_term(f),
    }
    if capture_convention:
        in_cone = -float(f.up[1]) > np.cos(np.radians(CAPTURE_CONE_DEG))
        terms["capture_convention"] = WEIGHTS["capture_convention"] if in_cone else 0.0
    if capture_up is not None:
        cos_pose = float(f.up @ capture_up)
        terms["capture_up"] = WEIGHTS["capture_up"] * (1.0 if cos_pose > np.cos(np.radians(POSE_CONE_DEG)) else
                                                      -1.0 if cos_pose < 0.0 else 0.0)
    return terms


def unit_capture_up(capture_up: ArrayLike | None) -> np.ndarray | None:
    """The mean camera up as a unit vector, or None when absent or degenerate (cameras pointing every way)."""
    if capture_up is None:
        return None
    v = np.asarray(capture_up, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"capture_up must be a finite 3-vector, got {v.tolist()}")
    n = float(np.linalg.norm(v))
    return None if n < 1e-6 else v / n


def decide(all_facts: list[CandidateFacts], capture_up: np.ndarray | None = None, capture_convention: bool = True,
           disabled: tuple[str, ...] = ()) -> UpDecision:
    """Score every candidate and compare the best with the best that levels differently.

    `capture_convention`: False for formats with an up convention of their own (glTF: +Y).
    `disabled`: evidence terms left out (the bench's ablation).
    """
    scored = []
    for f in all_facts:
        terms = {k: v for k, v in evidence_terms(f, all_facts, capture_up, capture_convention).items()
                 if k not in disabled}
        scored.append(ScoredCandidate(f, terms))
    ranked = tuple(sorted(scored, key=lambda c: -c.score))
    best = ranked[0]
    distinct_cos = np.cos(np.radians(DISTINCT_DEG))
    runner = next((c for c in ranked[1:] if float(c.up @ best.up) < distinct_cos), None)
    third = None if runner is None else next(
        (c for c in ranked[1:] if float(c.up @ best.up) < distinct_cos and float(c.up @ runner.up) < distinct_cos), None)
    margin = float("inf") if runner is None else best.score - runner.score
    confidence = 1.0 if runner is None else float(1.0 / (1.0 + np.exp(-CONFIDENCE_SLOPE * margin)))
    return UpDecision(ranked, runner, margin, confidence, third)


def _candidate_words(rec: UpCandidateRecord) -> str:
    up = ",".join(f"{x:.3g}" for x in rec["up"])
    if "floor_area_m2" in rec:
        return f"up {up} (floor {rec['floor_area_m2']:.3g} m2, storey {rec['storey_height_m']:.3g} m)"
    return f"up {up} (floor {rec['floor_area_units2']:.4g} units2, storey {rec['storey_height_units']:.4g} units)"


def ambiguity_line(name: str, candidates: list[UpCandidateRecord], margin: float | None) -> str:
    """One line naming both candidates (and a third, when recorded; source coordinates) and the flag that picks one."""
    first, second = candidates[0], candidates[1]
    by = "" if margin is None else f" by only {margin:.2f}"
    third = f" (next: {_candidate_words(candidates[2])})" if len(candidates) > 2 else ""
    return (f"{name}: up is ambiguous: {_candidate_words(first)} beats {_candidate_words(second)}{by}{third}; "
            f"pick one with --up=X,Y,Z (e.g. --up={','.join(f'{x:.3g}' for x in first['up'])}; API: spec "
            "field up or the space's chosen up), or accept the guess with --accept-up-guess (accept_up_guess)")
