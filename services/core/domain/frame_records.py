"""The JSON records of what ingest found about a scan's frame (up, units, point-cloud meshing): stored with
the space (`validation`), in job.json's space records and in the API's frame fields."""

from __future__ import annotations

from typing import NotRequired, TypedDict

from services.core.domain.capture_records import CaptureSummary
from services.core.domain.json_types import JSONObject


class UpCandidateRecord(TypedDict):
    """One candidate up: direction (source coordinates), score and its evidence terms; floor area and storey
    height in metres when the units are known, else in source units."""

    up: list[float]
    score: float
    evidence: dict[str, float]
    floor_fraction: float
    floor_area_m2: NotRequired[float]
    storey_height_m: NotRequired[float]
    floor_area_units2: NotRequired[float]
    storey_height_units: NotRequired[float]


class UpRecord(TypedDict):
    """How up was found and how sure; the scored candidates when the evidence decided it."""

    source_direction: list[float]
    method: str
    confidence: str  # high | low
    floor_area_m2: float
    floor_fraction: float
    runner_up_angle_deg: float | None
    margin: float | None
    probability: NotRequired[float | None]
    ambiguous: NotRequired[bool]
    evidence: NotRequired[dict[str, float]]
    candidates: NotRequired[list[UpCandidateRecord]]
    # why this up, in words: the evidence that set it apart, or the rule that gave it
    reason: NotRequired[str]
    # the geometry's own winner, when the file's frame overruled it
    geometry_prefers: NotRequired[UpCandidateRecord]


class UnitCandidateRecord(TypedDict):
    """One candidate unit: what it makes of the scan (storey, extents in metres), its score and evidence."""

    unit: str
    unit_scale: float
    storey_height_m: float
    extent_m: list[float]
    score: float
    evidence: dict[str, float]


class UnitsRecord(TypedDict):
    unit_scale: float
    unit: str
    reason: str
    ambiguous: NotRequired[bool]
    candidates: NotRequired[list[UnitCandidateRecord]]


class FrameRecord(TypedDict):
    """LoadedSpace.frame_record(): the keys present are the ones detected or given."""

    up: UpRecord
    units: NotRequired[UnitsRecord]
    reconstruction: NotRequired[JSONObject]  # point clouds: how they were meshed
    class_names: NotRequired[dict[str, str]]
    capture: NotRequired[CaptureSummary]
