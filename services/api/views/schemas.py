"""API models of a job's plan (cameras, points, views) and tasks."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from services.api.outputs.schemas import OutputLink


class TaskBrief(BaseModel):
    """A view's task of one cue: its state and, when failed, the error."""

    id: int
    state: str
    attempts: int
    error: str | None = None


class ViewRead(BaseModel):
    """View v of point p in a space (angles in degrees, pose as OpenCV world_to_camera, metres)."""

    space_id: int
    space: str
    point: int
    view: int
    camera: int
    fov_deg: float
    roll_deg: float
    obliqueness_deg: float
    resolution: int
    world_to_camera: list[float] = Field(description="16 floats, row-major, world -> OpenCV camera")
    state: str = Field(
        description="failed if a task failed; done when every task is done; else the least advanced"
    )
    tasks: dict[str, TaskBrief]
    outputs: dict[str, OutputLink] | None = Field(None, description="pre-signed links (with ?urls=true)")


class TaskRead(BaseModel):
    """One point-view-cue task."""

    id: int
    space_id: int
    point: int
    view: int
    cue: str
    state: str
    attempts: int
    worker_id: str | None
    error: str | None
    output_key: str | None
    size: int | None
    sha256: str | None
    duration_s: float | None
    queued_at: datetime | None
    started_at: datetime | None
    finished_at: datetime | None


class PlanSpace(BaseModel):
    """Cameras and points of one space, for a top-down plot (metres, world frame, +Z up)."""

    space_id: int
    name: str
    bounds: list[list[float]] | None = Field(None, description="[[minx,miny,minz],[maxx,maxy,maxz]]")
    cameras: list[list[float]] = Field(description="[x, y, z, yaw_rad] per camera")
    points: list[list[float]] = Field(description="[x, y, z, n_views] per point")
    views: list[list[int]] = Field(description="[point, camera] per view (first `max_items`)")
    truncated: bool = Field(description="true when a list was cut at max_items")


class Plan(BaseModel):
    """The plan of a job: per space, cameras and points."""

    job_id: int
    spaces: list[PlanSpace]


class ThroughputBucket(BaseModel):
    """Tasks that finished (done) in [t, t + bucket_s)."""

    t: datetime
    done: int


class Throughput(BaseModel):
    """Done tasks over time, from task finished_at, in equal buckets since the job started."""

    job_id: int
    bucket_s: float
    buckets: list[ThroughputBucket]
