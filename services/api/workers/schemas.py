"""API models of render workers."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field


class CurrentTask(BaseModel):
    """The task a worker is running (shown only when it belongs to one of the caller's jobs)."""

    id: int
    job_id: int
    cue: str
    space_id: int
    point: int
    view: int


class WorkerRead(BaseModel):
    """A worker process and its heartbeat."""

    id: str
    host: str
    queues: list[str]
    started_at: datetime
    last_heartbeat: datetime
    heartbeat_age_s: float = Field(description="seconds since the last heartbeat")
    alive: bool = Field(description="heartbeat younger than the staleness limit")
    busy: bool = Field(description="running a task (of any tenant)")
    current_task: CurrentTask | None
    tasks_done: int | None = Field(
        description="tasks finished, every tenant's: operators only (null for tenants)"
    )
    labels_per_s: float | None = Field(description="throughput over every tenant's work: operators only")
    labels: dict[str, int] = Field(
        default_factory=dict,
        description="labels per cue over every tenant's work: operators only ({} for tenants)",
    )
