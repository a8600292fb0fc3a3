"""Planning one space of a job: the steps the scheduler loop and `omnidata plan` share.

Both load the space in the job's frame, plan it with the generator seeded by the job seed and the space's
name (`space_rng`: the same plan whatever the order or number of spaces), and describe the result in the one
job.json space record (services.core.domain.job_document.space_record).
"""

from __future__ import annotations

from pathlib import Path
from typing import NotRequired, TypedDict

import numpy as np

from services.core.domain.capture_records import CapturePlanRecord
from services.core.domain.frame_records import FrameRecord
from services.core.domain.job_document import SpaceRecord, space_record
from services.core.domain.jobspec import JobSpec, SpaceFrame
from services.core.domain.plan import (
    CLIP_NOTES_IN_SUMMARY,
    ClipSummary,
    SpacePlan,
    ValidFractionSummary,
    clip_summary,
)
from services.core.domain.steering import PlanDistributions
from services.core.ingest.loading import LoadedSpace, load_space
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.cameras import detect_floors


class PlanSpaceSummary(FrameRecord):
    """One space's part of `job.plan_summary` (the scheduler adds the counts: PlannedSpaceSummary)."""

    shortfall: str | None
    valid_fraction: ValidFractionSummary | None
    clips: ClipSummary
    source_to_world: list[list[float]]
    bounds: list[list[float]]
    up_axis: str
    up_method: str
    unit_scale: float | str
    warnings: list[str]
    capture_plan: NotRequired[CapturePlanRecord]


class PlannedSpaceSummary(PlanSpaceSummary):
    """`job.plan_summary["spaces"][name]`: the summary and the counts the scheduler persisted."""

    cameras: int
    points: int
    views: int
    tasks: int
    plan_key: str
    distributions: dict[str, object] | None  # steering.PlanDistributions.record()


class JobPlanSummary(TypedDict):
    """`job.plan_summary` once planned (after a failed attempt: only `attempts`)."""

    spaces: dict[str, PlannedSpaceSummary]
    attempts: int
    shortfall: NotRequired[bool]
    planning_s: NotRequired[float]


class _CapturePlanPart(TypedDict, total=False):
    capture_plan: CapturePlanRecord  # capture plans only


def load_for_job(source: str | Path, spec: JobSpec, extract_dir: str | Path | None = None,
                 frame: SpaceFrame | None = None) -> LoadedSpace:
    """The space loaded in the frame the job's spec asks for (up_axis, up, unit_scale, source_to_world), or in
    `frame` (`load_space`'s frame keywords: a registered space's chosen up, `db.frame_choice`)."""
    return load_space(source, **(frame if frame is not None else spec.space_frame()), extract_dir=extract_dir)


def plan_space(loaded: LoadedSpace, spec: JobSpec, name: str) -> SpacePlan:
    """The plan of one space of a job (PlanError when the spec cannot be met at all)."""
    return make_plan(loaded, spec, space_rng(spec.seed, name), name)


def plan_summary_of(loaded: LoadedSpace, plan: SpacePlan, spec: JobSpec) -> PlanSpaceSummary:
    """What the scheduler keeps per space in `job.plan_summary` (JSON-ready; the counts are added by the
    caller)."""
    capture_part: _CapturePlanPart = {"capture_plan": plan.capture} if plan.capture is not None else {}
    return {
        "shortfall": plan.shortfall,
        "valid_fraction": plan.valid_fraction,
        "clips": clip_summary(plan.clip_notes, CLIP_NOTES_IN_SUMMARY),
        "source_to_world": np.asarray(loaded.source_to_world, dtype=float).tolist(),
        "bounds": np.asarray(loaded.bounds, dtype=float).tolist(),
        "up_axis": spec.up_axis, "up_method": loaded.up_method,
        "unit_scale": loaded.units.scale if loaded.units is not None else spec.unit_scale,
        "warnings": list(loaded.warnings),
        **loaded.frame_record(),
        **capture_part,
    }


def plan_record(loaded: LoadedSpace, plan: SpacePlan, spec: JobSpec, *, position: int, cues: list[str],
                plan_key: str) -> SpaceRecord:
    """The job.json space record of a space planned here (no database: `omnidata plan`)."""
    summary = plan_summary_of(loaded, plan, spec)
    return space_record(
        space_id=None, position=position, cues=cues, checksum=loaded.checksum,
        source_format=loaded.source_path.suffix.lower().lstrip("."),
        source_to_world=summary["source_to_world"], unit_scale=summary["unit_scale"], up_axis=spec.up_axis,
        bounds=summary["bounds"], face_count=loaded.face_count, has_texture=loaded.has_texture,
        has_semantics=loaded.has_semantics,
        counts={"cameras": len(plan.cameras), "points": len(plan.points), "views": len(plan.views)},
        shortfall=plan.shortfall, valid_fraction=plan.valid_fraction, clips=summary["clips"], plan=plan_key,
        warnings=summary["warnings"], frame=summary, distributions=plan_distributions(loaded, plan),
    )


def scan_floor_z(loaded: LoadedSpace) -> float | None:
    """The lowest floor of a world-frame scan (planning.cameras.detect_floors): what camera heights in
    job.json are measured from; None when it has none (object scans)."""
    floors = detect_floors(loaded.mesh)
    return floors[0].z if floors else None


def plan_distributions(loaded: LoadedSpace, plan: SpacePlan) -> dict[str, object]:
    """The job.json record of a whole plan's steering distributions (gathered as the scheduler does)."""
    gathered = PlanDistributions(scan_floor_z(loaded))
    gathered.add(plan)
    return gathered.record()
