"""API models of the designer routes."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from services.api.jobs.schemas import DbId
from services.core.domain.jobspec import JobSpec

MAX_SPACES = 8  # a preview plans each space in one process within one time budget
MAX_PREVIEWS = 8
MAX_YAML_CHARS = 100_000


class DesignRequest(BaseModel):
    """Spaces and a spec, as JSON (`spec`) or as the YAML a user edits (`spec_yaml`), not both."""

    model_config = ConfigDict(extra="forbid", strict=True)

    space_ids: list[DbId] = Field(
        min_length=1, max_length=MAX_SPACES, description="ids of your spaces, in order"
    )
    spec: JobSpec | None = Field(None, description="the steering knobs (default: all defaults)")
    spec_yaml: str | None = Field(
        None, max_length=MAX_YAML_CHARS, description="the same knobs as a YAML document"
    )
    previews: int = Field(
        4, ge=0, le=MAX_PREVIEWS, description="views to render small previews of (/previews)"
    )

    @field_validator("space_ids")
    @classmethod
    def _unique(cls, v: list[int]) -> list[int]:
        if len(set(v)) < len(v):
            raise ValueError("each space once")
        return v

    @model_validator(mode="after")
    def _one_spec(self) -> DesignRequest:
        if self.spec is not None and self.spec_yaml is not None:
            raise ValueError("give the spec as JSON (spec) or as YAML (spec_yaml), not both")
        return self


class SpaceDrawing(BaseModel):
    """What the page draws of one planned space (a sample of cameras, points and camera-point lines)."""

    id: int
    name: str
    shortfall: str | None
    counts: dict[str, int]
    bounds: list[list[float]] = Field(description="world-frame box, metres, +Z up")
    cameras: list[list[float]] = Field(description="[x, y, z] metres")
    points: list[list[float]] = Field(description="[x, y, z, views of the point]")
    lines: list[list[int]] = Field(
        description="[point index, camera index] into the lists above, one per view"
    )


class DesignPlan(BaseModel):
    """A spec's plan: the spec as JSON (knobs off their defaults) and YAML, spaces, distributions."""

    spec: dict[str, Any]
    yaml: str
    spaces: list[SpaceDrawing]
    histograms: dict[str, dict[str, list[float]]] = Field(description="name -> {edges, counts}: fixed edges")
    summary: dict[str, dict[str, float | None]] = Field(description="name -> quantiles, mean and n")
    planning_s: float


class Preview(BaseModel):
    """One sampled view's previews: readable PNGs (data URLs) of rgb, depth, normal and segments."""

    space: str
    point: int
    view: int
    fov_deg: float
    images: dict[str, str]


class DesignPreviews(BaseModel):
    """Previews of a few views spread over a spec's plan."""

    previews: list[Preview]
    render_s: float


class DesignFit(BaseModel):
    """A spec fitted to a space's posed capture: the spec (JSON and YAML), the two-sample KS statistic of each
    fitted distribution between the capture and the fitted plan, and the capture's histograms."""

    spec: dict[str, Any]
    yaml: str
    ks: dict[str, float]
    target: dict[str, dict[str, list[float]]]
    source: str
    frames: int
    fit_s: float
