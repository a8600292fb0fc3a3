"""JSON records of a posed capture: its summary (ingest), the colour camera the planner refined, and the
capture plan record that a SpacePlan carries to job.json, the dashboard and the workers."""

from __future__ import annotations

from typing import NotRequired, TypedDict


class CaptureSummary(TypedDict):
    """Capture.summary(): what job.json, the API and the dashboard show of a capture."""

    format: str
    frames: int
    has_photos: bool
    image_sizes: list[list[int | None]]  # [width, height] of each size the frames have
    focal_px: list[float] | None  # min, median, max
    distortion: list[str]
    problems: int
    problem_messages: list[str]
    notes: list[str]
    up_angle_deg: float | None
    K_first: NotRequired[list[list[float]]]


class ColourCorrectionRecord(TypedDict):
    """ColourCorrection.as_dict(): focal scale, principal point shift (px) and camera offset (m)."""

    focal_scale: float
    dcx: float
    dcy: float
    offset_m: list[float]


class RefinedCamera(TypedDict):
    """The planner's search for the colour camera (cameras.capture_refine); the workers apply `correction`."""

    correction: ColourCorrectionRecord
    score_before: float
    score_after: float
    frames_scored: int
    evaluations: int
    refined: str


class PhotoCoverage(TypedDict):
    mean: float
    min: float


class CapturePlanRecord(CaptureSummary):
    """A capture plan: the capture's summary, the views planned, their alignment and photo coverage, the views
    dropped per check and, when refined, the colour camera."""

    views: int
    alignment: dict[str, object]  # scheduler.planning.alignment.score_summary
    photo_coverage: PhotoCoverage | None
    dropped: NotRequired[dict[str, int]]
    view_alignment: NotRequired[dict[str, float | None]]  # "point/v" -> score
    min_photo_coverage: NotRequired[float]
    refined: NotRequired[RefinedCamera]
