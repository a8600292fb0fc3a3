"""Gravity (the up direction) of a scan from its geometry, in any orientation.

Frames: everything here is in the *source frame* (the coordinates `trimesh.load(source, force="mesh")`
gives, in the file's units); directions are unit 3-vectors in that frame.

1. *Plane families*: the dominant plane orientations of the scan, whatever its orientation
   (`plane_families`).
2. *Floor* (spaces scanned from inside, normals facing the free space): each family direction u, in
   both signs, is scored by the area facing +u in the lower half of the extent along u (a floor seen
   from above; halves rather than thin bands because a tilted floor spans part of the height) plus
   the surplus of area facing +u over area facing -u between the end bands (furniture tops face up
   and their bottoms are rarely scanned; walls at mid height face both ways). The scan is a room when some
   candidate's lower area covers >= 15 % of the convex cross-section of the scan across u. Walls also face
   inwards from both ends, but in pairs (no surplus) and over less area than the floor of a room that is
   wider than tall. The best score wins; a tie between the two signs of one family (a closed empty box) falls
   back to the file convention. The direction is refined to the area-weighted mean normal of the floor
   faces (the ceiling's, where a ceiling is the one plane the candidate shows), or set exactly to the
   source axis when the file's levelling decided (`up_evidence.AXIS_DEG`) or glTF's +Y did.
3. *Support base* (single objects, normals facing outwards): outward-facing area in the end 10 % of a
   family that covers >= 15 % of the cross-section and >= 3 times the opposite end (the flat base of
   the bunny): up points away from the base.
4. Otherwise the file convention: +Y up for .obj/.gltf/.glb, +Z up for .ply and point clouds.

Confidence (rooms): every candidate direction is scored on more evidence than plane area (what the file
says, furniture, the scan's extent, storey height, a single frame's view, capture poses when given;
`services.core.ingest.frame.up_evidence`), and the winner's margin over the best candidate that levels the
scan differently gives a calibrated confidence. Below the refusal margin the estimate is *ambiguous*: loading
refuses it unless guesses are accepted.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from services.core.domain.frame_records import UpRecord
from services.core.ingest.frame.candidates import CandidateFacts, FileFrame
from services.core.ingest.frame.plane_families import plane_families, with_axes
from services.core.ingest.frame.reason_words import METHOD_WORDS, reason_words
from services.core.ingest.frame.single_view import SingleView, frame_view, single_view
from services.core.ingest.frame.up_evidence import (
    ONE_END_RATIO,
    VIEW_PITCH_DEG,
    WEIGHTS,
    UpDecision,
    decide,
    nearest_axis,
    unit_capture_up,
)

CONVENTION_UP = {".obj": "+y", ".gltf": "+y", ".glb": "+y", ".ply": "+z"}
_SPECIFIED_UP = (".gltf", ".glb")  # formats whose specification fixes up (+Y)


def file_frame(suffix: str, cloud: bool = False, camera: bool = False, origin_camera: bool = False
               ) -> FileFrame:
    """What a file of this format says about its up before any floor is looked at (FileFrame's fields)."""
    return FileFrame(axis_vector(CONVENTION_UP.get(suffix, "+z")), suffix in _SPECIFIED_UP, cloud, camera,
                     origin_camera)


# The one floor rule: a floor face's normal lies within 15 degrees of up. The planner's detect_floors
# (services.scheduler.planning.cameras) uses the same cone, so a scan levelled here has the floors planned
# there.
FLOOR_CONE_DEG = 15.0
FLOOR_CONE_COS = float(np.cos(np.radians(FLOOR_CONE_DEG)))
_END_BAND = 0.10
# furniture lies between bands this wide at both ends: narrower ones take soffits, ceiling steps and lamps
# near a ceiling for furniture undersides (a phone scan's soffit 0.85-0.93 of the way up turned its sign)
_FURNITURE_BAND = 0.20
# floor area / the scan's cross-section: below it the scan is an object, not a room
_FLOOR_MIN_FRACTION = 0.15
_GIVEN_FLOOR_MIN_FRACTION = 0.10  # up given: a partial scan may see only a strip of its floor
_BASE_MIN_FRACTION = 0.15
_TIE_REL = 0.02
_BASE_DOMINANCE = 3.0
_SNAP_RAD = 1e-3  # a direction this close to a source axis is that axis (1 mm per metre)
# object bases are rougher than floors (the bunny's is 1.1 degrees off its axis)
_BASE_SNAP_RAD = np.radians(2.0)
_HULL_POINTS = 5_000
LOW_MARGIN = 1.25  # support bases: best area / runner-up below this is low confidence


@dataclass(frozen=True)
class UpEstimate:
    """The up direction of a scan in its source frame, how it was found and how sure we are."""

    up: np.ndarray  # unit vector, source frame
    method: str  # floor | base | convention | convention-tie | given | source_to_world | recorded_gravity
    floor_area: float = 0.0  # source units^2 of the faces taken as floor (0 when none)
    floor_fraction: float = 0.0  # floor area / convex cross-section of the scan across up
    runner_up_angle_deg: float | None = None  # angle between up and the runner-up candidate
    # rooms: score of up - runner-up's (log-odds); bases: area ratio; inf: no runner-up
    margin: float | None = None
    storey_height: float | None = None  # source units, floor to top (spaces with a floor)
    decision: UpDecision | None = None  # rooms: every candidate's evidence, the runner-up and the confidence

    @property
    def ambiguous(self) -> bool:
        """True when a room's winner does not clearly beat a candidate that levels it differently."""
        return self.decision is not None and self.decision.ambiguous

    @property
    def low_confidence(self) -> bool:
        """True when the runner-up came close or only a convention decided."""
        if self.method in ("given", "source_to_world"):
            return False
        if self.method in ("convention", "convention-tie"):
            return True
        if self.decision is not None:
            return self.decision.ambiguous
        return self.margin is not None and self.margin < LOW_MARGIN

    @property
    def confidence(self) -> float | None:
        """Calibrated probability that a room's up is right (None for objects, conventions and given
        frames)."""
        return None if self.decision is None else round(self.decision.confidence, 4)

    def doubt(self) -> str:
        """Why the estimate is low confidence, in words for a warning."""
        if self.method == "convention":
            return "no floor or support base was found, so the file format's convention decided"
        if self.method == "convention-tie":
            return "floor and ceiling look alike, so the file format's convention picked the sign"
        angle = "?" if self.runner_up_angle_deg is None else f"{self.runner_up_angle_deg:.0f}"
        if self.decision is not None:
            return f"{self.method}, scoring only {self.margin:.2f} above a candidate {angle} deg away"
        return f"{self.method}, scoring only {self.margin:.2f}x a candidate {angle} deg away"

    def record(self, unit_scale: float = 1.0) -> UpRecord:
        """JSON-ready summary (areas in m^2 with `unit_scale` metres per source unit)."""
        margin = None if self.margin is None else (
            None if not np.isfinite(self.margin) else round(self.margin, 3))
        out: UpRecord = {
            "source_direction": [float(x) for x in self.up],
            "method": self.method,
            "confidence": "low" if self.low_confidence else "high",
            "floor_area_m2": round(self.floor_area * unit_scale**2, 4),
            "floor_fraction": round(self.floor_fraction, 4),
            "runner_up_angle_deg": (None if self.runner_up_angle_deg is None
                                    else round(self.runner_up_angle_deg, 2)),
            "margin": margin,
        }
        if self.decision is not None:  # scored by the evidence: its probability, terms and candidates
            d = self.decision
            out["probability"] = self.confidence
            out["ambiguous"] = d.ambiguous
            out["evidence"] = d.best.record(unit_scale)["evidence"]
            out["candidates"] = [c.record(unit_scale) for c in d.shown]
            if d.geometry_prefers is not None:
                out["geometry_prefers"] = d.geometry_prefers.record(unit_scale)
        out["reason"] = (reason_words(self.decision) if self.decision is not None
                         else METHOD_WORDS[self.method])
        return out


def axis_vector(code: str) -> np.ndarray:
    """Unit vector of an axis name such as '+y' or '-z'."""
    v = np.zeros(3)
    v["xyz".index(code[1])] = 1.0 if code[0] == "+" else -1.0
    return v


def snap_to_axis(u: np.ndarray, tol_rad: float = _SNAP_RAD) -> np.ndarray:
    """`u` normalised, or exactly the source axis it lies within `tol_rad` of."""
    u = np.asarray(u, dtype=np.float64)
    u = u / np.linalg.norm(u)
    i = int(np.argmax(np.abs(u)))
    if abs(u[i]) >= np.cos(tol_rad):
        e = np.zeros(3)
        e[i] = np.sign(u[i])
        return e
    return u


def _cross_section(pts: np.ndarray, u: np.ndarray) -> float:
    """Area of the convex hull of the points projected on the plane across `u` (rotation invariant)."""
    a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    uv = np.column_stack([pts @ a, pts @ b])
    try:
        return float(ConvexHull(uv).volume)  # 2-D hull: volume is the area
    except (QhullError, ValueError):
        return 0.0


@dataclass(frozen=True)
class _Geometry:
    """The per-face and per-vertex arrays of a mesh, read once (trimesh re-hashes on every cached access)."""

    normals: np.ndarray
    areas: np.ndarray
    centers: np.ndarray
    vertices: np.ndarray
    hull_points: np.ndarray  # a subsample of the vertices for cross-sections

    @cached_property
    def gaze(self) -> np.ndarray:
        """The mean direction from the source origin to the surface (area-weighted unit directions): where
        the origin is the capture's camera, where it looked."""
        d = self.centers / np.maximum(np.linalg.norm(self.centers, axis=1, keepdims=True), 1e-300)
        mean = self.areas @ d
        n = float(np.linalg.norm(mean))
        return mean / n if n > 0 else mean

    @classmethod
    def of(cls, mesh: trimesh.Trimesh) -> _Geometry:
        v = np.asarray(mesh.vertices)
        step = len(v) // _HULL_POINTS + 1
        return cls(np.asarray(mesh.face_normals), np.asarray(mesh.area_faces),
                   np.asarray(mesh.triangles_center), v, v[::step])


# surface elements from elsewhere than a mesh's faces (a point cloud's planar samples: `point_planes`)
SurfaceSamples = _Geometry


@dataclass(frozen=True)
class _Candidate:
    up: np.ndarray
    score: float
    floor_area: float
    floor_fraction: float
    floor_faces: np.ndarray  # bool per face
    ceiling_faces: np.ndarray  # bool per face: facing down in the upper half
    height: float  # extent along up, source units
    cross_section: float  # convex cross-section across up, source units^2
    ceiling_area: float  # area facing down in the upper half
    mid_up: float  # area facing up between the end bands (furniture tops)
    mid_down: float  # area facing down between the end bands (furniture undersides, rarely scanned)
    origin_split: float  # the smaller share of the area on either side of the source origin's height
    origin_height: float  # the source origin's height above the floor (its faces' area-weighted mean)
    origin_gaze: float  # the sine of the elevation of the origin's mean gaze (`_Geometry.gaze`)

    def facts(self) -> CandidateFacts:
        """The measurements the evidence scoring needs."""
        ceiling = self.ceiling_area / self.cross_section if self.cross_section > 0 else 0.0
        return CandidateFacts(self.up, self.score, self.floor_area, self.floor_fraction, self.height,
                              self.cross_section, ceiling, self.mid_up, self.mid_down, self.origin_split,
                              self.origin_height, self.origin_gaze)


def _floor_candidate(geom: _Geometry, u: np.ndarray) -> _Candidate:
    normals, areas = geom.normals, geom.areas
    hv = geom.vertices @ u
    lo, hi = float(hv.min()), float(hv.max())
    h = geom.centers @ u
    c = normals @ u
    facing_up, facing_down = c > FLOOR_CONE_COS, c < -FLOOR_CONE_COS
    floor = facing_up & (h <= 0.5 * (lo + hi))  # <=: a scan of a flat floor alone has lo == hi
    floor_area = float(areas[floor].sum())
    band = _FURNITURE_BAND * (hi - lo)
    middle = (h > lo + band) & (h < hi - band)  # furniture, not floor or ceiling
    mid_up, mid_down = float(areas[facing_up & middle].sum()), float(areas[facing_down & middle].sum())
    band = _END_BAND * (hi - lo)
    wide_middle = (h > lo + band) & (h < hi - band)
    surplus = max(0.0, float(areas[facing_up & wide_middle].sum())
                  - float(areas[facing_down & wide_middle].sum()))
    cross = _cross_section(geom.hull_points, u)
    fraction = floor_area / cross if cross > 0 else 0.0
    ceiling = facing_down & (h >= 0.5 * (lo + hi))
    ceiling_area = float(areas[ceiling].sum())
    above = float(areas[h > 0.0].sum()) / max(float(areas.sum()), 1e-300)
    # the floor's mean height (tops in the lower half raise it: the camera then reads lower, never higher)
    origin_height = -float(np.average(h[floor], weights=areas[floor])) if floor_area > 0 else -lo
    return _Candidate(u, floor_area + surplus, floor_area, fraction, floor, ceiling, hi - lo, cross,
                      ceiling_area, mid_up, mid_down, min(above, 1.0 - above), origin_height,
                      float(geom.gaze @ u))


def _refine_up(geom: _Geometry, cand: _Candidate) -> np.ndarray:
    """`cand`'s up as the mean normal of the plane it shows: its floor, or its ceiling where that is the one
    plane it shows (a ceiling seen from below: what faces up under it is no plane)."""
    normals, areas = geom.normals, geom.areas
    sign, sel = 1.0, cand.floor_faces
    if cand.ceiling_area > ONE_END_RATIO * cand.floor_area:
        sign, sel = -1.0, cand.ceiling_faces
    up = cand.up
    for cone in (15.0, 5.0):
        s = sel & (sign * (normals @ up) > np.cos(np.radians(cone)))
        if not s.any():
            break
        mean = sign * (normals[s] * areas[s, None]).sum(axis=0)
        up = mean / np.linalg.norm(mean)
    return snap_to_axis(up)


def floor_evidence(mesh: trimesh.Trimesh, up: np.ndarray) -> UpEstimate | None:
    """The floor along a given up direction, or None when the scan has none (an object).

    Up is given, so less floor is needed than to find it: a partial scan may see only a strip of its floor.
    """
    cand = _floor_candidate(_Geometry.of(mesh), np.asarray(up, dtype=np.float64) / np.linalg.norm(up))
    if cand.floor_fraction < _GIVEN_FLOOR_MIN_FRACTION:
        return None
    return UpEstimate(cand.up, "given", cand.floor_area, cand.floor_fraction, storey_height=cand.height)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(float(a @ b), -1.0, 1.0))))


def estimate_up(mesh: trimesh.Trimesh, suffix: str, capture_up: np.ndarray | None = None,
                *, disabled_evidence: tuple[str, ...] = (), recorded_up: np.ndarray | None = None,
                samples: SurfaceSamples | None = None, file: FileFrame | None = None,
                view_points: np.ndarray | None = None,
                frame_axes: Callable[[], Sequence[np.ndarray]] | None = None) -> UpEstimate:
    """Up direction in the source frame, how it was found and how sure (see the module docstring).

    `capture_up`: the mean up vector of the capture's cameras in the source frame (-Y of OpenCV camera
    axes, averaged over the poses), when the caller has poses; strong evidence for rooms.
    `recorded_up`: up from a gravity the capture recorded (unit vector, source frame): the strongest
    evidence; up is then exactly it when the floor agrees, and it stands alone when no floor is found.
    `disabled_evidence`: evidence terms left out (the bench's ablation). `samples`: surface elements that
    stand in for the mesh's faces (a point cloud's own planes). `file`: what the file says (`file_frame`).
    `view_points`: a point cloud's own points: its single view is judged on them (`frame_view`), since its
    mesh extrapolates and trims the frame's surfaces; without them, on the vertices (`single_view`).
    `frame_axes`: a cloud's plane directions read from its points (`point_planes`), asked for where its
    single view's mesh shows no plane near the frame's short side (`_lost_floor_axes`).
    """
    conv = axis_vector(CONVENTION_UP.get(suffix, "+z"))
    cam_up = unit_capture_up(capture_up)
    rec_up = unit_capture_up(recorded_up)
    geom = samples if samples is not None else _Geometry.of(mesh)
    view = single_view(geom.vertices) if view_points is None else frame_view(view_points)
    families = plane_families(geom.normals, geom.areas)
    if frame_axes is not None:
        families = with_axes(families, _lost_floor_axes(families, view, frame_axes))
    if not families:
        return UpEstimate(conv, "convention") if rec_up is None else _recorded_alone(geom, rec_up)
    cands = [_floor_candidate(geom, s * f) for f, _ in families for s in (1.0, -1.0)]
    if any(c.floor_fraction >= _FLOOR_MIN_FRACTION for c in cands):
        decision = decide([c.facts() for c in cands], cam_up, file or file_frame(suffix), disabled_evidence,
                          view, rec_up)
        best = next(c for c in cands if c.up is decision.best.up)
        runner = decision.runner_up
        angle = _angle_deg(best.up, runner.up) if runner is not None else None
        if (rec_up is None and runner is not None and angle is not None and angle > 179.0
                and _alike(best.facts(), runner.facts)):
            # floor and ceiling alike (a closed, empty box): no evidence can pick, the file convention does
            sign = float(np.sign(conv @ best.up)) or 1.0
            return UpEstimate(snap_to_axis(sign * best.up), "convention-tie", best.floor_area,
                              best.floor_fraction, angle, decision.margin, best.height)
        if rec_up is not None and decision.best.terms.get("recorded_gravity", 0.0) > 0:
            up = rec_up  # measured gravity is exact where a scanned floor's mean normal is not
        elif decision.best.terms.get("levelled_axis", 0.0) > 0:
            # the exporter's levelling is exact; a scanned floor's mean normal is not
            up = nearest_axis(best.up)
        elif decision.best.terms.get("format_up", 0.0) >= WEIGHTS["format_up_binding"]:
            up = file_frame(suffix).axis  # the specification's up, which the floor confirmed
        else:
            up = _refine_up(geom, best) if best.floor_area + best.ceiling_area > 0 else snap_to_axis(best.up)
        return UpEstimate(up, "floor", best.floor_area, best.floor_fraction, angle, decision.margin,
                          best.height, decision)
    if rec_up is not None:
        return _recorded_alone(geom, rec_up)
    base = _support_base(geom, [f for f, _ in families])
    return base if base is not None else UpEstimate(conv, "convention")


def _lost_floor_axes(families: list[tuple[np.ndarray, float]], view: SingleView | None,
                     frame_axes: Callable[[], Sequence[np.ndarray]]) -> list[np.ndarray]:
    """The directions of `frame_axes` near a landscape frame's short side (where up lies, the camera pitched
    at most `VIEW_PITCH_DEG`) when no family of its mesh lies there: a far, noisy floor that the mesh lost and
    the frame's points still show."""
    if view is None or view.short_axis is None:
        return []
    short = view.short_axis
    def near(axis: np.ndarray) -> bool:
        return abs(float(axis @ short)) >= np.cos(np.radians(VIEW_PITCH_DEG))
    return [] if any(near(f) for f, _ in families) else [a for a in frame_axes() if near(a)]


def _recorded_alone(geom: _Geometry, rec_up: np.ndarray) -> UpEstimate:
    """Up from recorded gravity where no floor was found; the scan's extent along it is its storey."""
    heights = geom.vertices @ rec_up
    return UpEstimate(rec_up, "recorded_gravity", storey_height=float(np.ptp(heights)))


def guess_candidates(mesh: trimesh.Trimesh, suffix: str, samples: SurfaceSamples | None = None,
                     file: FileFrame | None = None, view_points: np.ndarray | None = None
                     ) -> UpDecision | None:
    """Every plane-family direction scored as an up candidate, for a scan where no floor was found (None: no
    planes).

    Offered when such a scan is space-sized: its up would otherwise be the file format's guess. `samples`,
    `file` and `view_points`: as `estimate_up`'s."""
    geom = samples if samples is not None else _Geometry.of(mesh)
    families = plane_families(geom.normals, geom.areas)
    if not families:
        return None
    facts = [_floor_candidate(geom, s * f).facts() for f, _ in families for s in (1.0, -1.0)]
    view = single_view(geom.vertices) if view_points is None else frame_view(view_points)
    return decide(facts, None, file or file_frame(suffix), view=view)


def up_candidate_facts(mesh: trimesh.Trimesh) -> list[CandidateFacts]:
    """What each plane-family direction (both signs) measures as an up candidate (the bench's ablation)."""
    geom = _Geometry.of(mesh)
    return [_floor_candidate(geom, s * f).facts() for f, _ in plane_families(geom.normals, geom.areas)
            for s in (1.0, -1.0)]


def _alike(a: CandidateFacts, b: CandidateFacts) -> bool:
    """Two opposite candidates that look the same from both sides: floor and ceiling areas, no furniture."""
    return (abs(a.area_score - b.area_score) <= _TIE_REL * max(a.area_score, b.area_score)
            and a.mid_up + a.mid_down <= _TIE_REL * a.area_score)


def _support_base(geom: _Geometry, axes: list[np.ndarray]) -> UpEstimate | None:
    normals, areas, centers = geom.normals, geom.areas, geom.centers
    found: list[tuple[float, np.ndarray, float]] = []
    for f in axes:
        hv = geom.vertices @ f
        lo, hi = float(hv.min()), float(hv.max())
        band = _END_BAND * (hi - lo)
        h, c = centers @ f, normals @ f
        cross = max(_cross_section(geom.hull_points, f), 1e-300)
        at_low = float(areas[(h <= lo + band) & (c < -FLOOR_CONE_COS)].sum())  # base at the low end: up = +f
        at_high = float(areas[(h >= hi - band) & (c > FLOOR_CONE_COS)].sum())
        for base, opposite, up in ((at_low, at_high, f), (at_high, at_low, -f)):
            if base >= _BASE_MIN_FRACTION * cross and base >= _BASE_DOMINANCE * opposite:
                found.append((base, up, base / cross))
    if not found:
        return None
    found.sort(key=lambda t: -t[0])
    base, up, fraction = found[0]
    margin = base / found[1][0] if len(found) > 1 else float("inf")
    angle = _angle_deg(up, found[1][1]) if len(found) > 1 else None
    return UpEstimate(snap_to_axis(up, _BASE_SNAP_RAD), "base", 0.0, 0.0, angle, margin)
