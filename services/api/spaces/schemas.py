"""API models of spaces (separate from the ORM row `services.core.db.models.Space`)."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.core.db.frame_choice import needs_frame
from services.core.db.models import Space
from services.core.domain.cues import default_cues
from services.core.domain.frame_values import MAX_UNIT_SCALE, parse_unit_scale
from services.core.domain.keys import check_name
from services.core.ingest.frame.resolve import frame_of

UpAxis = Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z"]


class SpaceOptions(BaseModel):
    """How to read a scan: its name, up axis and unit scale (metres per source unit)."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, description="unique per tenant; default: the file name without extension")
    up_axis: UpAxis = Field(
        "auto", description="source axis pointing up; auto detects floors in any orientation"
    )
    unit_scale: float | Literal["auto"] = Field(
        "auto", description="metres per source unit, or auto (from the storey height of rooms)",
        json_schema_extra={
            "anyOf": [{"type": "number", "exclusiveMinimum": 0, "maximum": 1000}, {"const": "auto"}]
        },
    )

    @field_validator("name")
    @classmethod
    def _name(cls, v: str | None) -> str | None:
        return None if v is None else check_name("name", v)

    @field_validator("unit_scale", mode="plain")
    @classmethod
    def _scale(cls, v: object) -> float | str:
        return parse_unit_scale(v, numbers_as_text=True)  # multipart form fields are text


class SpaceRegister(SpaceOptions):
    """Register a scan already in the service's object store (uploaded there directly, e.g. with the AWS
    CLI)."""

    model_config = ConfigDict(extra="forbid", strict=True)  # a JSON body, unlike the upload's form fields

    key: str | None = Field(
        None,
        min_length=1,
        max_length=1024,
        description="object key under `uploads/<your tenant>/` in the service's store",
    )
    uri: str | None = Field(
        None,
        min_length=1,
        max_length=2048,
        description="the same object as a URI of the service's store "
        "(s3://bucket/prefix/uploads/<tenant>/...)",
    )

    @field_validator("unit_scale", mode="plain")
    @classmethod
    def _scale(cls, v: object) -> float | str:
        return parse_unit_scale(v)  # strict: a JSON number (or "auto"), never a numeric string


class UpChoice(BaseModel):
    """The frame a person picked for a space: its up in the scan's source coordinates and/or its units."""

    model_config = ConfigDict(extra="forbid", strict=True)

    up: list[float] | None = Field(
        None, min_length=3, max_length=3,
        description="[x, y, z], source coordinates; any length (omitted: the detected up)",
    )
    unit_scale: float | None = Field(
        None, gt=0, le=MAX_UNIT_SCALE,
        description="metres per source unit, when the "
        "units were ambiguous (omitted: the upload's, or chosen from the storey)",
    )

    @field_validator("up")
    @classmethod
    def _finite(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (not all(math.isfinite(x) for x in v) or math.hypot(*v) < 1e-9):
            raise ValueError(f"up {v} must be a finite, non-zero direction [x, y, z]")
        return v

    @field_validator("unit_scale", mode="before")
    @classmethod
    def _number(cls, v: object) -> object:
        return float(v) if isinstance(v, int) and not isinstance(v, bool) else v


class SpaceRead(BaseModel):
    """A registered space and what validation found in it."""

    id: int
    name: str
    source_key: str
    source_format: str
    checksum: str = Field(description="sha256 hex of the uploaded bytes")
    unit_scale: float
    up_axis: str
    bounds: list[list[float]] | None = Field(
        None, description="[[minx,miny,minz],[maxx,maxy,maxz]] in metres, world frame"
    )
    source_to_world: list[list[float]] | None = None
    face_count: int
    vertex_count: int
    has_texture: bool
    has_semantics: bool
    supported_cues: list[str] = Field(description="cues a job may request for this space")
    validation: dict[str, Any] | None = None
    frame: dict[str, Any] | None = Field(
        None, description="how the frame was found: up (source direction, method, confidence, probability, "
        "evidence, the two best candidates), units, reconstruction"
    )
    needs_frame: bool = Field(False, description="up detection could not decide and nobody has picked one: "
                              "jobs are refused until PUT /spaces/{id}/up (or a job spec that sets up)")
    up_choice: dict[str, Any] | None = Field(
        None, description="the up a person picked (source coordinates), by whom"
    )
    created_at: datetime

    @classmethod
    def from_row(cls, s: Space) -> SpaceRead:
        """Build from the ORM row."""
        return cls(
            id=s.id,
            name=s.name,
            source_key=s.source_key,
            source_format=s.source_format,
            checksum=s.checksum,
            unit_scale=s.unit_scale,
            up_axis=s.up_axis,
            bounds=s.bounds,
            source_to_world=s.source_to_world,
            face_count=s.face_count,
            vertex_count=s.vertex_count,
            has_texture=s.has_texture,
            has_semantics=s.has_semantics,
            supported_cues=default_cues(s.has_semantics),
            validation=s.validation,
            frame=frame_of(s.validation),
            needs_frame=needs_frame(s),
            up_choice=(s.validation or {}).get("up_choice"),
            created_at=s.created_at,
        )
