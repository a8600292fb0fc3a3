"""API models of jobs and their progress (separate from the ORM rows and from the JobSpec value object)."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.core.db.models import TASK_STATES
from services.core.domain.jobspec import JobSpec

DbId = Annotated[int, Field(ge=1, le=2**63 - 1)]


def _walk(value: object, path: str) -> None:
    # JSON allows NaN/Infinity and NUL characters in strings; Postgres JSONB stores neither, and a
    # non-finite coordinate is never meaningful: refuse them with the field's path.
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{path or 'spec'} must be a finite number, got {value}")
    if isinstance(value, str) and "\x00" in value:
        raise ValueError(f"{path or 'spec'} contains a NUL character")
    if isinstance(value, dict):
        for k, v in value.items():
            _walk(v, f"{path}.{k}" if path else str(k))
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            _walk(v, f"{path}.{i}" if path else str(i))


class JobCreate(BaseModel):
    """A job request: the spaces to render (in order) and the JobSpec knobs."""

    model_config = ConfigDict(extra="forbid", strict=True)  # "3" or true is not a space id

    space_ids: list[DbId] = Field(min_length=1, max_length=256, description="ids of your spaces, in order")
    spec: JobSpec = Field(default_factory=lambda: JobSpec.model_validate({}), description="steering knobs")

    @field_validator("space_ids")
    @classmethod
    def _unique(cls, v: list[int]) -> list[int]:
        dupes = sorted({i for i in v if v.count(i) > 1})
        if dupes:
            raise ValueError(f"space ids repeat: {', '.join(map(str, dupes))}")
        return v

    @field_validator("spec")
    @classmethod
    def _storable(cls, v: JobSpec) -> JobSpec:
        _walk(v.model_dump(mode="python"), "")
        return v


class CueProgress(BaseModel):
    """Task counts of one cue by state."""

    by_state: dict[str, int]
    total: int
    done: int
    fraction: float = Field(description="finished (done, failed or cancelled) / total, 0..1")


class Progress(BaseModel):
    """Task counts of a job by state (from the incremental counters), throughput and ETA."""

    total: int
    by_state: dict[str, int] = Field(description=f"every task state: {', '.join(TASK_STATES)}")
    finished: int = Field(description="done + failed + cancelled")
    fraction: float = Field(description="finished / total, 0..1")
    throughput_per_s: float | None = Field(
        None, description="tasks finished per second (last minute, else average)"
    )
    labels_per_s: float | None = Field(None, description="output files (internal passes excluded) per second")
    eta_s: float | None = Field(
        None, description="seconds until the remaining tasks finish at this throughput"
    )


class JobSpaceRead(BaseModel):
    """A space of a job and the cues it renders there."""

    space_id: int
    name: str
    position: int
    cues: list[str]
    frame: dict[str, Any] | None = Field(
        None,
        description="once planned: up (source direction, method, confidence), units and, for point clouds, "
        "the reconstruction",
    )


class JobRead(BaseModel):
    """A job with its live progress."""

    id: int
    name: str
    state: str
    priority: int
    error: str | None
    paused_by: str | None = Field(
        None, description="'storage': the service paused the job because its object store failed (full, "
        "or S3 answering 5xx); `error` says how, and the job resumes on its own once the store takes writes "
        "again. null: not paused, or paused by you")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    total_tasks: int
    space_ids: list[int]
    progress: Progress
    cues: dict[str, CueProgress] = Field(description="per cue: task counts by state")


class JobDetail(JobRead):
    """A job with its spec, spaces and plan summary."""

    spec: dict[str, Any]
    spaces: list[JobSpaceRead]
    output_root: str
    plan_summary: dict[str, Any] | None


class JobEvent(BaseModel):
    """What the SSE routes send when a job's counters or state change."""

    id: int
    name: str
    state: str
    error: str | None
    progress: Progress
    cues: dict[str, CueProgress]
