"""job.json: one schema, written by `omnidata plan` (stage "plan") and by finished jobs (stage "render").

A consumer reads the same keys whichever command made the file; a value that a stage cannot know is null
(a plan has no job id, no task counts in the database). `format` names the schema version: readers check it
before relying on a key. The schema is documented in docs/conventions.md ("job.json").
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import TypedDict

from services.core.domain.camera import CONVENTIONS
from services.core.domain.cues import CATALOG
from services.core.domain.plan import ClipSummary, ValidFractionSummary

JOB_FORMAT = "omnidata.job/2"
LAYOUT = "<cue>/<component>/<space>/point_<p>_view_<v>_domain_<cue>.<ext>"
STAGES = ("plan", "render")
# what LoadedSpace.frame_record() may hold; always present in a space record (null when not detected/given)
FRAME_RECORD_KEYS = ("up", "units", "reconstruction", "class_names", "capture", "capture_plan")


class CueEncoding(TypedDict):
    ext: str
    encoding: str
    dtype: str
    channels: int
    per_point: bool
    inputs: list[str]


class FileCounts(TypedDict):
    by_state: dict[str, int]
    by_cue: dict[str, dict[str, int]]
    total: int


class SpaceCounts(TypedDict):
    cameras: int | None
    points: int | None
    views: int | None


class SpaceRecord(TypedDict):
    """One space of job.json (see space_record)."""

    space_id: int | None
    position: int
    cues: list[str]
    checksum_sha256: str
    source_format: str
    source_to_world: list[list[float]] | None
    unit_scale: float | str | None
    up_axis: str
    bounds_world_m: list[list[float]] | None
    face_count: int
    has_texture: bool
    has_semantics: bool
    counts: SpaceCounts
    tasks: int | None
    shortfall: str | None
    valid_fraction: ValidFractionSummary | None
    clips: ClipSummary | None
    plan: str | None
    warnings: list[str]
    # the frame record (FRAME_RECORD_KEYS): open JSON objects written by ingest, null when not detected/given
    up: object
    units: object
    reconstruction: object
    class_names: object
    capture: object
    capture_plan: object
    # steering facts (services.core.domain.steering.PlanDistributions.record): floor_z, summary, histograms
    distributions: object


class JobDocument(TypedDict):
    """The whole job.json document (see job_document)."""

    format: str
    stage: str
    code_version: str
    job: dict[str, object]
    component: str
    spec: dict[str, object]
    layout: str
    conventions: dict[str, str]
    cues: dict[str, CueEncoding]
    spaces: dict[str, SpaceRecord]
    plan_summary: dict[str, object]
    counts: FileCounts


def code_version() -> str:
    """Version of the code that produced a job or plan: $OMNIDATA_CODE_VERSION, else the package's version
    plus the git commit when run from a checkout (`0.1.0+g0123456789ab`)."""
    env = os.environ.get("OMNIDATA_CODE_VERSION")
    if env:
        return env
    try:
        version = metadata.version("omnidata-service")
    except metadata.PackageNotFoundError:
        version = "unknown"
    git = Path(__file__).resolve().parents[3] / ".git"
    try:
        head = (git / "HEAD").read_text().strip()
        if head.startswith("ref: "):
            ref = git / head[5:]
            head = ref.read_text().strip() if ref.is_file() else head
        return f"{version}+g{head[:12]}"
    except OSError:  # not a checkout (or a worktree, whose .git is a file)
        return version


def cue_encodings(cues: Iterable[str]) -> dict[str, CueEncoding]:
    """How each cue's files are stored (extension, encoding, dtype, channels), from the cue catalog."""
    return {
        n: {
            "ext": CATALOG[n].ext,
            "encoding": CATALOG[n].encoding,
            "dtype": CATALOG[n].dtype,
            "channels": CATALOG[n].channels,
            "per_point": CATALOG[n].per_point,
            "inputs": [i for i in CATALOG[n].inputs if not CATALOG[i].internal],
        }
        for n in cues
    }


def file_counts(by_cue: Mapping[str, Mapping[str, int]]) -> FileCounts:
    """Task (or file) counts as {by_state, by_cue, total} from {cue: {state: n}}."""
    by_state: dict[str, int] = {}
    for states in by_cue.values():
        for state, n in states.items():
            by_state[state] = by_state.get(state, 0) + n
    return {
        "by_state": by_state, "by_cue": {c: dict(s) for c, s in by_cue.items()},
        "total": sum(by_state.values()),
    }


def space_record(
    *,
    space_id: int | None,
    position: int,
    cues: Sequence[str],
    checksum: str,
    source_format: str,
    source_to_world: list[list[float]] | None,
    unit_scale: float | str | None,
    up_axis: str,
    bounds: list[list[float]] | None,
    face_count: int,
    has_texture: bool,
    has_semantics: bool,
    counts: Mapping[str, int | None],
    shortfall: str | None,
    valid_fraction: ValidFractionSummary | None,
    clips: ClipSummary | None,
    plan: str | None,
    warnings: Sequence[str],
    frame: Mapping[str, object],
    distributions: object = None,
) -> SpaceRecord:
    """One space of job.json: the source, its frame (source_to_world, up, units), its plan and counts."""
    return {
        "space_id": space_id,
        "position": position,
        "cues": list(cues),
        "checksum_sha256": checksum,
        "source_format": source_format,
        "source_to_world": source_to_world,
        "unit_scale": unit_scale,
        "up_axis": up_axis,
        "bounds_world_m": bounds,
        "face_count": face_count,
        "has_texture": has_texture,
        "has_semantics": has_semantics,
        "counts": {
            "cameras": counts.get("cameras"), "points": counts.get("points"), "views": counts.get("views"),
        },
        "tasks": counts.get("tasks"),  # tasks compiled by the scheduler; null for a plan
        "shortfall": shortfall,
        "valid_fraction": valid_fraction,
        "clips": clips,
        "plan": plan,
        "warnings": list(warnings),
        "up": frame.get("up"),
        "units": frame.get("units"),
        "reconstruction": frame.get("reconstruction"),
        "class_names": frame.get("class_names"),
        "capture": frame.get("capture"),
        "capture_plan": frame.get("capture_plan"),
        "distributions": distributions,
    }


def job_document(
    *,
    stage: str,
    job: Mapping[str, object],
    component: str,
    spec: Mapping[str, object],
    cues: Iterable[str],
    spaces: Mapping[str, SpaceRecord],
    plan_summary: Mapping[str, object],
    counts: Mapping[str, Mapping[str, int]],
) -> JobDocument:
    """The whole job.json document (see the module docstring); `job` is the job row's summary."""
    if stage not in STAGES:
        raise ValueError(f"stage {stage!r} is not one of {STAGES}")
    return {
        "format": JOB_FORMAT,
        "stage": stage,
        "code_version": code_version(),
        "job": dict(job),
        "component": component,
        "spec": dict(spec),
        "layout": LAYOUT,
        "conventions": dict(CONVENTIONS),
        "cues": cue_encodings(cues),
        "spaces": dict(spaces),
        "plan_summary": dict(plan_summary),
        "counts": file_counts(counts),
    }


def job_json_bytes(document: JobDocument) -> bytes:
    """job.json as written to a file: indented, keys sorted (the same bytes for the same document)."""
    return (json.dumps(document, indent=2, sort_keys=True) + "\n").encode("utf-8")
