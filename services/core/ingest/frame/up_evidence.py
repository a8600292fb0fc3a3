"""Evidence for each up candidate of a room scan, combined into one score and a calibrated confidence.

Frames and units: the source frame and the file's units (unknown here: every term is unit free).
A candidate is a plane-family direction `u` (one sign) proposed by `services.core.ingest.frame.gravity`. Each
term below is a log-odds contribution; a candidate's score is their sum, and the decision compares the best
candidate with the best one that would level the scan differently (more than `DISTINCT_DEG` away):

- `floor_area`: the floor seen from above plus the furniture surplus (gravity's area score), as the log
  of its ratio to the best candidate's. Plane area alone is what fails on partial scans: a wall or a
  row of cabinet fronts can be as large as the visible floor.
- `furniture`: furniture tops face up and their undersides are rarely scanned: the horizontal area between
  bands of a fifth of the height at both ends (soffits and lamps sit nearer the ceiling), facing up minus
  facing down over their sum, from +1 (tops seen) to -1 (the ceiling taken as floor). It decides the sign of
  a family; cabinet fronts score along a wall's normal too, which is why it weighs less than `extent`.
- `extent`: rooms are wider than tall. Height along `u` over the square root of the cross-section
  across `u`, as the log of its ratio to the thinnest candidate's (a wall taken as floor turns the
  room's width into its "height"). On the real rooms of bench/ingest/ingest_real.py it ranks the floor's
  family first in every multi-view room: the heaviest geometric term.
- `storey`: whether the extent along `u` is a storey (2.2-3.5 m, or 1.2-3.5 m for a scan without a
  ceiling: partial scans rarely see it) in one of the units we accept; a penalty when it fits none.
- `levelled_axis`: a plausible floor within `AXIS_DEG` of a source axis. A random orientation puts a given
  direction that close to one of the six axis directions with odds of about 1 in 1,000, while people and
  devices export levelled files far more often than rotated ones: strong evidence that the file is levelled.
  When the walls are axis-aligned too, every family gets it and the rest of the evidence picks among them.
  Exporters write levelled files with up on the format's up axis, not upside down: a family on that axis
  showing one plane (no floor-ceiling pair) gets it on the format's sign only, whichever side the plane is
  seen from. On another axis both signs get it (a PLY in a level camera's frame has its up on -Y). The axes
  a convention puts up on count (`UP_AXES`: Y for glTF, OBJ, ARKit and a level camera's -Y; Z for PLY,
  ScanNet and Matterport), X only where plane families lie on two axes or more (a levelled file turned by
  quarter turns): a camera held unrolled that pitches turns a fused scan about X and leaves its side walls
  there, the only family on an axis. And only where the geometry does not rule the candidate out
  (`FILE_TRUST`). Tilted so about a wall's axis, 16 real scans were planned on that wall, 90 degrees off, at a
  stated 93% or more, in 39 of 168 cases (bench/ingest/ingest_real.py's `tilted_about_a_wall`); now in 13,
  all tilted about Y or Z, where the geometry puts that wall at most 1.51 behind the floor or ahead of it.
- `mirror`: one plane and no opposite one is a floor seen from above or a ceiling seen from below (what hangs
  below a ceiling looks like furniture standing on a floor), so the geometry's lead of one sign of such a
  family over the other is capped at `MIRROR_CAP` (`MIRROR_CAP_CLOUD`, below the margin, for a point cloud,
  whose sides were estimated, unless its camera saw it from within: `_mirror_cap`): the file, cameras or a
  recorded gravity can overrule it.
- `format_up`: the candidate on the format's own up axis (`FileFrame`): glTF's +Y is the specification's
  (binding, as strong as an axis-aligned floor, for a floor within `FORMAT_DEG` of it); PLY's +Z and OBJ's +Y
  are habits, weighted below `REFUSE_MARGIN` (Y-up PLYs and Z-up OBJs are common): they order a refusal, they
  never decide alone.
- `camera_frame`: a point cloud stored in an OpenCV camera's frame (`camera_frame`: the origin sees it, it
  lies ahead along +Z) was taken by an upright camera: a candidate within 60 degrees of -Y and 15 of the Y-Z
  plane gains as a habit does, below `REFUSE_MARGIN` (a turned copy can look like an upside-down camera's
  frame): with a cloud's capped geometry (`mirror`) agreeing, it decides the sign; alone, it orders a
  refusal.
- `camera_height`: a cloud whose origin is its camera (`FileFrame.origin_camera`): a candidate whose floor
  lies further below that camera than a storey (`camera_place`), in every unit that makes the scan a room's
  height, is a ceiling taken for a floor (a tall ceiling over a camera is common, a camera held that high
  over a floor is not). An origin hovering over a room without its ceiling passes for a camera too, so it
  weighs just above the cloud's capped sign (`MIRROR_CAP_CLOUD`) and, with one habit against it, stays below
  `REFUSE_MARGIN`: it orders a refusal, never decides.
- `camera_looked_down`: a cloud whose origin is its camera (`camera_place`): a candidate under which that
  camera, at most a storey over the floor, saw everything below its own height and looked down at it (not
  straight down: a wall it faced) is a floor looked down at, not a ceiling looked up at from just below,
  where the camera's place singles that candidate out (it looked down so at no other, nor level across
  another). Hand-held captures look level or down: every cloud of bench/ingest/ingest_real.py whose origin
  is its camera looked between 44 degrees down and 2 up, but the ceiling-only captures, which looked up from
  4.5 m under their ceilings (`camera_height`). With a cloud's capped sign (`MIRROR_CAP_CLOUD`) agreeing, it
  decides a floor-only cloud's sign: a ceiling-only capture taken from under a storey's ceiling would be
  levelled upside down.
- `capture_up`: the mean up vector of the capture's cameras (-Y of OpenCV cameras, averaged), when the
  caller has poses. Cameras are held upright, give or take their pitch: strong evidence.
- `recorded_gravity`: the gravity a capture recorded with the scan (`recorded_gravity`): an IMU's or a
  dataset's measured down, precise to a degree or two. The strongest single term: a candidate within
  `RECORDED_CONE_DEG` of it gains, any other loses. When no candidate agrees with it, or the geometry alone
  clearly levels the scan another way (a stale file beside a re-exported mesh), the decision is ambiguous
  (`UpDecision.gravity_conflict`).
- `view_direction`, `view_aspect`: a single view (`services.core.ingest.frame.single_view`): up lies across
  the view direction within the camera's pitch (`VIEW_PITCH_DEG`; a wall the camera faced is no floor), near
  the frustum's short axis (landscape frames). `extent` is left out for it: a frustum's extent is not the
  room's.

The confidence is a logistic function of the margin (best score minus the runner-up's), fitted on the real
rooms of bench/ingest/ingest_real.py; below `REFUSE_MARGIN` (`SINGLE_VIEW_REFUSE_MARGIN` for one depth frame)
the estimate is ambiguous and planning does not go ahead on it unless the user accepted guesses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from services.core.ingest.frame.camera_place import CAMERA_SPLIT_MIN, camera_looked_down, camera_too_high
from services.core.ingest.frame.candidates import CandidateFacts, FileFrame, ScoredCandidate
from services.core.ingest.frame.single_view import SingleView

DISTINCT_DEG = 30.0  # candidates closer than this level the scan the same way
# score margin below which the estimate is ambiguous: on the real rooms of bench/ingest/ingest_real.py (as
# delivered, levelled, rotated) no wrong winner scored more than 0.85 above its runner-up with these weights
REFUSE_MARGIN = 1.2
# one depth frame: on the real frames of bench/ingest/ingest_real.py wrong winners led by up to 4.4 (a floor
# out of view)
SINGLE_VIEW_REFUSE_MARGIN = 4.5
# logistic slope of P(right | margin): the likeliest on bench/ingest/ingest_real.py's real rooms while a wrong
# winner still reached 1.65; none does now, so the probability it states above REFUSE_MARGIN (>= 88 %) is
# conservative
CONFIDENCE_SLOPE = 1.7
VIEW_PITCH_DEG = 50.0  # a depth camera pointed further up or down than this sees no room
CAMERA_FRAME_DEG = 10.0  # a single view looking this close to +Z is stored in its camera's (OpenCV) frame
POSE_CONE_DEG = 45.0
# an upright camera: pitched up to 60 degrees (a table seen from above), rolled up to 15 (the real frames of
# bench/ingest/ingest_real.py: up to 10); a turned copy of a camera's frame is rarely that upright
CAMERA_PITCH_COS = float(np.cos(np.radians(60.0)))
CAMERA_ROLL_SIN = float(np.sin(np.radians(15.0)))
RECORDED_CONE_DEG = 15.0  # a plane family this close to recorded gravity is its floor (the floor cone)
STOREY_M = (2.2, 3.5)
OPEN_STOREY_M = (1.2, 3.5)  # no ceiling scanned
UNIT_SCALES = (1.0, 0.01, 0.001, 0.0254)

AXIS_DEG = 1.5  # a floor this close to a source axis was levelled by whoever exported the file
UP_AXES = (1, 2)  # the source axes a levelled file's up lies on (Y, Z): X is no convention's up
# a floor this close to the up a format's specification fixes is that up (a drifted scan's floor)
FORMAT_DEG = 5.0
# what the file says counts for a candidate the geometry does not rule out: one this far below the geometry's
# best (a wall left on an axis by a tilt about it) is no floor, whatever the file's axes. On
# bench/ingest/ingest_real.py the levelled floors the file's axis decides lie at most 1.48 below (a Kinect
# frame), one 3DMatch fragment's at 5.1 (asked); the walls of its scans tilted about their axis
# (`tilted_about_a_wall`) 0-3.6 below. The two ranges overlap (walls at 1.45 and 1.51): this bound keeps every
# levelled floor and holds back the walls from 1.58 below on
FILE_TRUST = 1.7
# a family flat over this share of the cross-section at both ends holds a floor and a ceiling (a pair); with
# one plane only, the geometry's preference between its two signs is capped at MIRROR_CAP (`_mirror_terms`).
# No measure separated the ceiling-only captures of bench/ingest/ingest_real.py from its floor-only rooms
# (support heights, walls near the plane, point mass, extent); a cap below REFUSE_MARGIN would refuse every
# rotated floor-only room, so it only bounds the stated probability (0.93)
PAIR_FRACTION = 0.3
MIRROR_CAP = 1.5
# A point cloud's sides come from normals estimated without its sensor's positions (a table top above the
# viewpoint they were turned to faces down), and on the held-out clouds of bench/ingest/ingest_real.py its
# sign led by the full MIRROR_CAP on the wrong side: its geometry orders a cloud's two signs and decides
# them only with a second, independent sign (an upright camera's frame, the format's up axis) agreeing
MIRROR_CAP_CLOUD = 0.3
# ... unless its origin is its camera (`FileFrame.origin_camera`: its normals were turned towards it, so its
# sides are seen as a scanner's faces are), that camera saw the family on both sides of its own height
# (`camera_place.CAMERA_SPLIT_MIN`: it looked across the room) and the family shows one plane (its flat end
# this many times the other's: a corridor's floor and ceiling strips alike leave the sign to the furniture,
# which a low camera sees from below): then it is capped as a mesh's (`_mirror_cap`)
ONE_END_RATIO = 3.0
SIGN_FREE_TERMS = ("floor_area", "furniture", "extent", "storey")  # the geometry a mirror image keeps

WEIGHTS = {
    "levelled_axis": 6.0,
    "format_up_binding": 6.0,
    "format_up_habit": 1.0,
    "camera_frame": 1.0,
    "camera_height": 0.4,
    "camera_looked_down": 1.0,
    "floor_area": 1.0,
    "furniture": 3.0,
    "extent": 6.0,
    "storey": 0.5,
    "capture_up": 4.0,
    "recorded_gravity": 8.0,
    "view_direction": 6.0,
    "view_aspect": 3.0,
}


def _on_axis(u: np.ndarray, axis: np.ndarray) -> bool:
    return float(u @ axis) >= np.cos(np.radians(AXIS_DEG))


def nearest_axis(u: np.ndarray) -> np.ndarray:
    """The signed source axis nearest to the unit vector `u`."""
    e = np.zeros(3)
    i = int(np.argmax(np.abs(u)))
    e[i] = np.sign(u[i]) or 1.0
    return e


def source_axis_of(u: np.ndarray) -> int | None:
    """The source axis (0, 1, 2: X, Y, Z) the unit vector `u` lies within `AXIS_DEG` of, or None."""
    return int(np.argmax(np.abs(u))) if _on_axis(u, nearest_axis(u)) else None


@dataclass(frozen=True)
class UpDecision:
    """The scored candidates (best first), the runner-up that levels differently and how sure we are."""

    ranked: tuple[ScoredCandidate, ...]
    runner_up: ScoredCandidate | None
    margin: float  # best score - runner-up score (inf without a runner-up)
    confidence: float  # calibrated P(the best is right | margin), 0.5-1
    # the best candidate levelling differently from both (shown on refusal)
    third: ScoredCandidate | None = None
    # the geometry's own winner, when the file's frame overruled it
    geometry_prefers: ScoredCandidate | None = None
    refuse_below: float = REFUSE_MARGIN  # the margin a winner needs (`_required_margin`)
    # a recorded gravity that the geometry alone clearly contradicts (a stale file beside a re-exported mesh?)
    gravity_conflict: bool = False

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
        """True when the winner does not clearly beat a candidate that levels the scan differently, or a
        recorded gravity and the geometry disagree."""
        return self.margin < self.refuse_below or self.gravity_conflict


def _furniture_term(f: CandidateFacts) -> float:
    """+1 when mid-height horizontal surfaces all face up (tops seen, undersides not), -1 when all face
    down."""
    total = f.mid_up + f.mid_down
    return 0.0 if total <= 0 else (f.mid_up - f.mid_down) / total


def _storey_term(f: CandidateFacts) -> float:
    lo, hi = STOREY_M if f.ceiling_fraction >= 0.3 else OPEN_STOREY_M
    fits = any(lo <= f.height * s <= hi for s in UNIT_SCALES)
    return 0.0 if fits else -1.0


def _file_terms(f: CandidateFacts, file: FileFrame, plausible: bool, levelled_axes: tuple[int, ...],
                one_plane: bool, looked_down: bool) -> dict[str, float]:
    """What the file says of this candidate (see the module docstring). `plausible`: it could be the floor;
    `levelled_axes`: the source axes on which a floor means a levelled export (`_levelled_axes`); `one_plane`:
    its family shows one plane, a floor or a ceiling, and exporters write levelled files with up on the
    format's up axis, not upside down; `looked_down`: the one candidate the camera at the origin looked down
    at (`_camera_looked_down`)."""
    on_axis = plausible and source_axis_of(f.up) in levelled_axes
    # the sign prior holds on the format's up axis only: a PLY's -Y is a camera frame's up (y down), as
    # common as an ARKit +Y
    upside_down = one_plane and float(f.up @ file.axis) < -0.99
    terms = {"levelled_axis": WEIGHTS["levelled_axis"] if on_axis and not upside_down else 0.0}
    if file.binding:
        near = float(f.up @ file.axis) >= np.cos(np.radians(FORMAT_DEG))
        terms["format_up"] = WEIGHTS["format_up_binding"] if near and plausible else 0.0
    else:
        terms["format_up"] = WEIGHTS["format_up_habit"] if _on_axis(f.up, file.axis) else 0.0
    if file.origin_camera:
        terms["camera_height"] = -WEIGHTS["camera_height"] if camera_too_high(f) else 0.0
        terms["camera_looked_down"] = WEIGHTS["camera_looked_down"] if looked_down else 0.0
    if file.camera:  # an upright camera (image y down): pitched, hardly rolled
        upright = -float(f.up[1]) >= CAMERA_PITCH_COS and abs(float(f.up[0])) <= CAMERA_ROLL_SIN
        terms["camera_frame"] = WEIGHTS["camera_frame"] if upright else 0.0
    return terms


def _view_terms(f: CandidateFacts, view: SingleView) -> dict[str, float]:
    along = float(f.up @ view.direction)
    terms = {"view_direction": -WEIGHTS["view_direction"]
             if abs(along) > np.sin(np.radians(VIEW_PITCH_DEG)) else 0.0}
    if view.short_axis is not None:
        across = f.up - along * view.direction
        alignment = abs(float(across @ view.short_axis)) / max(float(np.linalg.norm(across)), 1e-12)
        terms["view_aspect"] = WEIGHTS["view_aspect"] * (2.0 * alignment - 1.0)
    return terms


def evidence_terms(f: CandidateFacts, all_facts: list[CandidateFacts], capture_up: np.ndarray | None,
                   view: SingleView | None = None, recorded_up: np.ndarray | None = None) -> dict[str, float]:
    """The log-odds terms of the geometry (and capture poses) for one candidate among all (module
    docstring)."""
    best_area = max(c.area_score for c in all_facts)
    ratios = [c.height / np.sqrt(c.cross_section) for c in all_facts if c.cross_section > 0 and c.height > 0]
    thinnest = min(ratios) if ratios else 1.0
    ratio = f.height / np.sqrt(f.cross_section) if f.cross_section > 0 and f.height > 0 else 10 * thinnest
    terms = {
        "floor_area": 0.0 if best_area <= 0 else  # no candidate sees any floor (a space-sized guess)
        WEIGHTS["floor_area"] * float(np.log(max(f.area_score, 1e-12 * best_area) / best_area)),
        "furniture": WEIGHTS["furniture"] * _furniture_term(f),
        "extent": -WEIGHTS["extent"] * float(np.log(ratio / thinnest)),
        "storey": WEIGHTS["storey"] * _storey_term(f),
    }
    if view is not None:
        del terms["extent"]
        terms.update(_view_terms(f, view))
    if capture_up is not None:
        cos_pose = float(f.up @ capture_up)
        terms["capture_up"] = WEIGHTS["capture_up"] * (
            1.0 if cos_pose > np.cos(np.radians(POSE_CONE_DEG)) else -1.0 if cos_pose < 0.0 else 0.0)
    if recorded_up is not None:
        near = float(f.up @ recorded_up) > np.cos(np.radians(RECORDED_CONE_DEG))
        terms["recorded_gravity"] = WEIGHTS["recorded_gravity"] * (1.0 if near else -1.0)
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


def _with_file_terms(geometry: list[ScoredCandidate], file: FileFrame, view: SingleView | None,
                     disabled: tuple[str, ...]) -> list[ScoredCandidate]:
    """The candidates scored on the geometry, with what the file says added (see `_file_terms`)."""
    best_geometry = max(c.score for c in geometry)
    # the file's axes count for a floor candidate the geometry does not rule out (FILE_TRUST)
    floor = {id(c): c.facts.plausible_floor
             and c.score >= best_geometry - FILE_TRUST for c in geometry}
    flips = [_flip(c, geometry) for c in geometry]
    one_plane = [f is not None and _one_plane(c, f) for c, f in zip(geometry, flips, strict=True)]
    # one plane on an axis: the file was levelled whichever side it is seen from, and the sign is the file's
    plausible = [floor[id(c)] or (o and f is not None and floor[id(f)])
                 for c, f, o in zip(geometry, flips, one_plane, strict=True)]
    looked_down = (camera_looked_down([c.facts for c in geometry]) if file.origin_camera
                   else [False] * len(geometry))
    axes = _levelled_axes(geometry, view)
    return [ScoredCandidate(c.facts, {**c.terms, **{k: v for k, v in _file_terms(
        c.facts, file, p, axes, o, d).items() if k not in disabled}})
        for c, p, o, d in zip(geometry, plausible, one_plane, looked_down, strict=True)]


def _levelled_axes(geometry: list[ScoredCandidate], view: SingleView | None) -> tuple[int, ...]:
    """The source axes on which a plausible floor means a levelled file: none in a depth frame's own camera
    frame (there it only means a camera held level); Y and Z (`UP_AXES`); X too where plane families lie on
    two axes or more (an axis-aligned file turned by quarter turns, not a scan pitched about X)."""
    if view is not None and float(view.direction[2]) >= np.cos(np.radians(CAMERA_FRAME_DEG)):
        return ()
    on_axes = {source_axis_of(c.up) for c in geometry} - {None}
    return (0, 1, 2) if len(on_axes) >= 2 else UP_AXES


def _flip(c: ScoredCandidate, candidates: list[ScoredCandidate]) -> ScoredCandidate | None:
    """The candidate of the same family with the opposite sign, if scored."""
    return next((o for o in candidates if float(o.up @ c.up) < -0.999), None)


def _one_plane(c: ScoredCandidate, flip: ScoredCandidate) -> bool:
    """True when the family of `c` shows no floor-ceiling pair: at most one end of it is flat (a floor seen
    from above and a ceiling seen from below are then mirror images)."""
    pair = (min(c.facts.floor_fraction, c.facts.ceiling_fraction) >= PAIR_FRACTION
            or min(flip.facts.floor_fraction, flip.facts.ceiling_fraction) >= PAIR_FRACTION)
    return not pair


def _mirror_cap(c: ScoredCandidate, file: FileFrame | None) -> float:
    """How far the geometry may prefer one sign of `c`'s one-plane family (constants above)."""
    if file is None or not file.cloud:
        return MIRROR_CAP
    ends = sorted((c.facts.floor_fraction, c.facts.ceiling_fraction))
    sides_seen = (file.origin_camera and c.facts.origin_split >= CAMERA_SPLIT_MIN
                  and ends[1] >= ONE_END_RATIO * ends[0])
    return MIRROR_CAP if sides_seen else MIRROR_CAP_CLOUD


def _mirror_terms(geometry: list[ScoredCandidate], file: FileFrame | None) -> list[ScoredCandidate]:
    """One plane seen from one side is a floor seen from above or a ceiling seen from below: what hangs below
    a ceiling (lamps, ducts, soffits) looks like what stands on a floor (tops seen, undersides not, at
    furniture heights), and its area is a floor's. The geometry's preference for one sign of such a family is
    capped at `cap` (MIRROR_CAP; MIRROR_CAP_CLOUD for a point cloud; term `mirror` lifts the other sign), so
    the file, cameras or a recorded gravity decide the sign where they speak."""
    out = []
    for c in geometry:
        flip = _flip(c, geometry)
        lift = 0.0
        if flip is not None and _one_plane(c, flip):
            def sign_free(x: ScoredCandidate) -> float:
                return sum(v for k, v in x.terms.items() if k in SIGN_FREE_TERMS)
            lift = max(0.0, sign_free(flip) - _mirror_cap(c, file) - sign_free(c))
        out.append(ScoredCandidate(c.facts, {**c.terms, "mirror": lift}) if lift > 0 else c)
    return out


def decide(all_facts: list[CandidateFacts], capture_up: np.ndarray | None = None,
           file: FileFrame | None = None, disabled: tuple[str, ...] = (),
           view: SingleView | None = None, recorded_up: np.ndarray | None = None) -> UpDecision:
    """Score every candidate and compare the best with the best that levels differently.

    `file`: what the file says (format, axes); None scores the geometry (and capture poses) alone.
    `disabled`: evidence terms left out (the bench's ablation). `view`: the scan is a single view.
    `recorded_up`: the up a recorded gravity gives (unit vector, source frame).
    """
    geometry = [ScoredCandidate(f, {k: v for k, v in evidence_terms(
        f, all_facts, capture_up, view, recorded_up).items() if k not in disabled}) for f in all_facts]
    if view is None and "mirror" not in disabled:  # a single view's frustum keeps it (`_view_terms`)
        geometry = _mirror_terms(geometry, file)
    scored = geometry if file is None else _with_file_terms(geometry, file, view, disabled)
    ranked = tuple(sorted(scored, key=lambda c: -c.score))
    best = ranked[0]
    runner = _first_distinct(ranked[1:], (best,))
    third = None if runner is None else _first_distinct(ranked[1:], (best, runner))
    margin = float("inf") if runner is None else best.score - runner.score
    confidence = 1.0 if runner is None else float(1.0 / (1.0 + np.exp(-CONFIDENCE_SLOPE * margin)))
    geometry_best = max(geometry, key=lambda c: c.score)
    geometry_prefers = (None if float(geometry_best.up @ best.up) >= np.cos(np.radians(DISTINCT_DEG))
                        else geometry_best)
    return UpDecision(ranked, runner, margin, confidence, third, geometry_prefers,
                      _required_margin(best, view), _gravity_conflict(ranked, view))


def _gravity_conflict(ranked: tuple[ScoredCandidate, ...], view: SingleView | None) -> bool:
    """True when the recording and the scan tell two different ups: no plane family agrees with the recorded
    gravity, or without it the geometry would level the scan differently by a margin it would plan on."""
    best = ranked[0]
    if "recorded_gravity" not in best.terms:
        return False
    if best.terms["recorded_gravity"] < 0:
        return True
    def without(c: ScoredCandidate) -> float:
        return c.score - c.terms["recorded_gravity"]
    geometry_best = max(ranked, key=without)
    if float(geometry_best.up @ best.up) >= np.cos(np.radians(DISTINCT_DEG)):
        return False
    return without(geometry_best) - without(best) >= _required_margin(geometry_best, view)


def _required_margin(best: ScoredCandidate, view: SingleView | None) -> float:
    """The margin a winner needs: more for a single depth frame (a frustum shows less of a room), and a square
    frame's geometry alone never suffices (nothing tells its rows from its columns) unless the file (or a
    recorded gravity) says. A frame's winner the camera faced (`view_direction`) is no floor however far it
    leads: only its own mirror image, faced the same way, was left to beat."""
    if view is None:
        return REFUSE_MARGIN
    if best.terms.get("view_direction", 0.0) < 0:
        return float("inf")
    file_says = (best.terms.get("levelled_axis", 0.0) > 0
                 or best.terms.get("format_up", 0.0) > WEIGHTS["format_up_habit"]
                 or best.terms.get("recorded_gravity", 0.0) > 0)
    return SINGLE_VIEW_REFUSE_MARGIN if view.short_axis is not None or file_says else float("inf")


def _first_distinct(ranked: tuple[ScoredCandidate, ...], others: tuple[ScoredCandidate, ...]
                    ) -> ScoredCandidate | None:
    """The first candidate that levels the scan differently from every one of `others`."""
    distinct_cos = np.cos(np.radians(DISTINCT_DEG))
    return next((c for c in ranked if all(float(c.up @ o.up) < distinct_cos for o in others)), None)
