"""A space's plan as plain data (cameras, points of interest, views) and its JSON form; the plan-stage cues
built from it are in services.core.domain.plan_cues.

Frames and units: world frame in metres, +Z up (the space's frame after `source_to_world`); angles in
radians; `world_to_camera` is 4x4 into OpenCV camera axes (x right, y down, z forward); pixel
coordinates are continuous with the centre of pixel u at u + 0.5 (services.core.domain.camera.CONVENTIONS).
No trimesh objects here: the worker and the API read plans without loading meshes.
"""

from __future__ import annotations

import json
import weakref
from dataclasses import dataclass
from typing import NotRequired, TypedDict

import numpy as np
from numpy.typing import ArrayLike

from services.core.domain.camera import (
    camera_center,
    intrinsics,
)
from services.core.domain.capture_records import CapturePlanRecord

PLAN_FORMAT = "omnidata.plan/1"
CAMERA_SOURCES = ("generated", "provided", "object", "capture")


class PlanError(ValueError):
    """A plan that cannot be made from these inputs (an impossible combination), with the reason."""


def frozen_array(a: ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    """`a` as a read-only float64 array of `shape` (ValueError otherwise): value objects cannot be changed
    through an array they hand out."""
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"expected shape {shape}, got {arr.shape}")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class CameraPose:
    """A camera position (world metres); fixated views choose the rotation per point."""

    idx: int
    position: np.ndarray  # (3,)
    source: str  # generated | provided | object
    uuid: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", frozen_array(self.position, (3,)))
        if self.source not in CAMERA_SOURCES:
            raise ValueError(f"camera source {self.source!r} is not one of {CAMERA_SOURCES}")


@dataclass(frozen=True, eq=False)
class PointOfInterest:
    """A surface point (world metres) with its unit normal and every camera with line of sight to it."""

    idx: int
    position: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit, facing the cameras that see it
    uuid: str
    camera_idxs: tuple[int, ...]  # all cameras with line of sight (not only those with views)

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", frozen_array(self.position, (3,)))
        object.__setattr__(self, "normal", frozen_array(self.normal, (3,)))
        object.__setattr__(self, "camera_idxs", tuple(np.asarray(self.camera_idxs, dtype=np.int64).tolist()))


@dataclass(frozen=True, eq=False)
class PlannedView:
    """View v of a point: a camera fixated on the point (world_to_camera maps it to the image centre)."""

    point_idx: int
    v: int  # 0..n-1 within the point
    camera_idx: int  # the camera it was taken from (trajectory frames: the nearest camera)
    world_to_camera: np.ndarray  # (4, 4) world metres -> OpenCV camera axes
    fov: float  # radians, horizontal = vertical (square images)
    roll: float  # radians about the optical axis relative to gravity (camera.look_at)
    resolution: int  # square image size, pixels
    obliqueness: float  # radians between the point normal and the direction to the camera
    in_sight: bool  # line of sight from the camera centre to the point
    alignment: float | None = None  # capture views: photo/geometry alignment score (~1 chance)
    photo_coverage: float | None = None  # views with photo rgb: predicted share of pixels a photo covers

    def __post_init__(self) -> None:
        object.__setattr__(self, "world_to_camera", frozen_array(self.world_to_camera, (4, 4)))

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world metres."""
        return camera_center(self.world_to_camera)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsics in pixels."""
        return intrinsics(self.fov, self.resolution)


class ValidFractionSummary(TypedDict):
    """Predicted share of each view's pixels with a surface: quantiles over the views (or a sample of
    `sampled_of` views, when only reported) and how many fell below `threshold`."""

    views: int
    threshold: float
    dropped: int
    probe_px: NotRequired[int]
    min: NotRequired[float]
    p05: NotRequired[float]
    p25: NotRequired[float]
    median: NotRequired[float]
    p75: NotRequired[float]
    max: NotRequired[float]
    mean: NotRequired[float]
    sampled_of: NotRequired[int]


class ClipNoteRecord(TypedDict):
    """A trajectory clip cut short or dropped: point_idx (None when dropped), outcome, frames kept and
    planned, and frames failed per check (keys of CLIP_CHECKS)."""

    point_idx: int | None
    outcome: str  # shortened | dropped
    frames: int
    planned_frames: int
    reasons: dict[str, int]


@dataclass(frozen=True, eq=False)
class SpacePlan:
    """Everything sampled for one space of a job. Views are sorted by (point_idx, v)."""

    space_name: str
    cameras: tuple[CameraPose, ...]
    points: tuple[PointOfInterest, ...]
    views: tuple[PlannedView, ...]
    shortfall: str | None = None
    # predicted share of pixels with a surface per view (summary)
    valid_fraction: ValidFractionSummary | None = None
    # trajectory clips cut short or dropped by the motion/clearance/visibility checks: point_idx (None
    # when dropped), outcome, frames, planned_frames, reasons {check: failed frames}
    clip_notes: tuple[ClipNoteRecord, ...] = ()
    capture: CapturePlanRecord | None = None  # capture plans: frames used and dropped, alignment distribution

    def views_of(self, point_idx: int) -> tuple[PlannedView, ...]:
        """The views of one point, v = 0..n-1."""
        return plan_index(self).by_point.get(point_idx, ())

    def view(self, point_idx: int, v: int) -> PlannedView:
        """View v of a point; KeyError when there is none."""
        views = self.views_of(point_idx)
        if not 0 <= v < len(views):
            raise KeyError(f"point {point_idx} has no view {v} ({len(views)} views)")
        return views[v]


CLIP_NOTES_IN_SUMMARY = 50  # clip notes copied into a job summary / job.json (the plan JSON has all)

# The checks a trajectory frame must pass (services.scheduler.planning.trajectory), as clip_notes name them.
CLIP_CHECKS = {
    "clearance": "closer to the mesh than cameras.clearance_m",
    "outside": "a surface between the frame and its route (outside the free space)",
    "hidden": "the point is not in sight",
    "turn": "the direction of motion turns faster than views.trajectory_max_turn_deg_per_m",
    "view": "the camera rotates faster than views.trajectory_max_view_deg_per_m",
    "route": "no route through free space to another camera that sees the point (for fixated clips, "
             "on which the view turns slowly enough)",
    "short": "the route through free space is shorter than views.trajectory_min_frames",
}


class ClipSummary(TypedDict):
    """Clips shortened and dropped, frames failed per check, and the first notes."""

    shortened: int
    dropped: int
    failed_frames: dict[str, int]
    notes: list[ClipNoteRecord]


def clip_summary(clip_notes: tuple[ClipNoteRecord, ...], max_notes: int = 0) -> ClipSummary:
    """Counts of trajectory clips shortened and dropped, of the frames that failed each check, and the
    first max_notes notes themselves (a job summary stays small; the plan JSON holds them all)."""
    failed: dict[str, int] = {}
    for note in clip_notes:
        for k, n in note["reasons"].items():
            failed[k] = failed.get(k, 0) + int(n)
    return {
        "shortened": sum(n["outcome"] == "shortened" for n in clip_notes),
        "dropped": sum(n["outcome"] == "dropped" for n in clip_notes),
        "failed_frames": dict(sorted(failed.items())),
        "notes": list(clip_notes[:max_notes]),
    }


def clip_shortfall(clip_notes: tuple[ClipNoteRecord, ...], n_points: int) -> str | None:
    """One line on the clips the checks cut short or dropped, most frequent failure first."""
    if not clip_notes:
        return None
    s = clip_summary(clip_notes)
    why = ", ".join(
        f"{CLIP_CHECKS[k]} ({n})" for k, n in sorted(s["failed_frames"].items(), key=lambda kv: -kv[1])
    )
    return (
        f"trajectory clips of {n_points} points: {s['shortened']} shortened, {s['dropped']} dropped "
        f"(failed, in frames or for route in clips: {why}); per clip in the plan's clip_notes"
    )


class PlanIndex:
    """Lookups kept beside (not inside) a frozen plan: views by point, points seen by each camera,
    positions."""

    def __init__(self, plan: SpacePlan):
        by_point: dict[int, list[PlannedView]] = {}
        for view in plan.views:
            by_point.setdefault(view.point_idx, []).append(view)
        self.by_point = {k: tuple(sorted(v, key=lambda x: x.v)) for k, v in by_point.items()}
        seen_by: dict[int, list[int]] = {}
        for p in plan.points:
            for c in p.camera_idxs:
                seen_by.setdefault(c, []).append(p.idx)
        self.points_seen_by = {c: np.array(v, dtype=np.int64) for c, v in seen_by.items()}
        self.positions = (
            np.stack([p.position for p in plan.points]) if plan.points else np.zeros((0, 3))
        )


_INDEXES: weakref.WeakKeyDictionary[SpacePlan, PlanIndex] = weakref.WeakKeyDictionary()


def plan_index(plan: SpacePlan) -> PlanIndex:
    """The plan's index, built on first use and dropped with the plan."""
    idx = _INDEXES.get(plan)
    if idx is None:
        idx = _INDEXES[plan] = PlanIndex(plan)
    return idx


# ---------------------------------------------------------------------------------------------
# JSON


class CameraRecord(TypedDict):
    idx: int
    position: list[float]
    source: str
    uuid: str


class PointRecord(TypedDict):
    idx: int
    position: list[float]
    normal: list[float]
    uuid: str
    camera_idxs: list[int]


class ViewRecord(TypedDict):
    point_idx: int
    v: int
    camera_idx: int
    world_to_camera: list[list[float]]
    fov: float
    roll: float
    resolution: int
    obliqueness: float
    in_sight: bool
    alignment: NotRequired[float]
    photo_coverage: NotRequired[float]


class PlanRecord(TypedDict):
    """A SpacePlan as JSON (format PLAN_FORMAT)."""

    format: str
    space_name: str
    shortfall: str | None
    valid_fraction: ValidFractionSummary | None
    clip_notes: list[ClipNoteRecord]
    cameras: list[CameraRecord]
    points: list[PointRecord]
    views: list[ViewRecord]
    capture: NotRequired[CapturePlanRecord]


def _view_record(v: PlannedView) -> ViewRecord:
    record: ViewRecord = {
        "point_idx": v.point_idx, "v": v.v, "camera_idx": v.camera_idx,
        "world_to_camera": np.asarray(v.world_to_camera, dtype=np.float64).tolist(), "fov": float(v.fov),
        "roll": float(v.roll), "resolution": int(v.resolution), "obliqueness": float(v.obliqueness),
        "in_sight": bool(v.in_sight),
    }
    if v.alignment is not None:
        record["alignment"] = v.alignment
    if v.photo_coverage is not None:
        record["photo_coverage"] = v.photo_coverage
    return record


def plan_to_dict(plan: SpacePlan) -> PlanRecord:
    """The plan as JSON-ready data (lists of floats, exact round trip)."""
    record: PlanRecord = {
        "format": PLAN_FORMAT,
        "space_name": plan.space_name,
        "shortfall": plan.shortfall,
        "valid_fraction": plan.valid_fraction,
        "clip_notes": list(plan.clip_notes),
        "cameras": [
            {"idx": c.idx, "position": np.asarray(c.position, dtype=np.float64).tolist(), "source": c.source,
             "uuid": c.uuid}
            for c in plan.cameras
        ],
        "points": [
            {
                "idx": p.idx, "position": np.asarray(p.position, dtype=np.float64).tolist(),
                "normal": np.asarray(p.normal, dtype=np.float64).tolist(), "uuid": p.uuid,
                "camera_idxs": list(p.camera_idxs),
            }
            for p in plan.points
        ],
        "views": [_view_record(v) for v in plan.views],
    }
    if plan.capture is not None:
        record["capture"] = plan.capture
    return record


def plan_to_json(plan: SpacePlan) -> str:
    """Deterministic JSON text of a plan (sorted keys, shortest round-trip floats)."""
    return json.dumps(plan_to_dict(plan), sort_keys=True, separators=(",", ":"), allow_nan=False)


def plan_from_dict(data: PlanRecord) -> SpacePlan:
    """Inverse of plan_to_dict."""
    if data.get("format") != PLAN_FORMAT:
        raise ValueError(f"not a plan: format {data.get('format')!r}, expected {PLAN_FORMAT!r}")
    return SpacePlan(
        space_name=data["space_name"],
        cameras=tuple(
            CameraPose(c["idx"], np.asarray(c["position"]), c["source"], c["uuid"]) for c in data["cameras"]
        ),
        points=tuple(
            PointOfInterest(
                p["idx"], np.asarray(p["position"]), np.asarray(p["normal"]), p["uuid"],
                tuple(p["camera_idxs"]),
            )
            for p in data["points"]
        ),
        views=tuple(
            PlannedView(
                v["point_idx"], v["v"], v["camera_idx"], np.asarray(v["world_to_camera"]), v["fov"],
                v["roll"], v["resolution"], v["obliqueness"], v["in_sight"], v.get("alignment"),
                v.get("photo_coverage"),
            )
            for v in data["views"]
        ),
        shortfall=data.get("shortfall"),
        valid_fraction=data.get("valid_fraction"),
        clip_notes=tuple(data.get("clip_notes", [])),
        capture=data.get("capture"),
    )


def plan_from_json(text: str | bytes) -> SpacePlan:
    """Inverse of plan_to_json."""
    return plan_from_dict(json.loads(text))


