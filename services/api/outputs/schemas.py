"""API models of output links."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field


class OutputLink(BaseModel):
    """A pre-signed link to one output file; it stops working at `expires_at`."""

    cue: str
    key: str = Field(description="object key relative to the job's output root")
    url: str
    expires_at: datetime
    size: int | None = None
    sha256: str | None = None
    content_type: str
    preview_url: str | None = Field(
        None,
        description="signed link to an 8-bit PNG preview (colour maps, palettes), made on first request and "
        "cached",
    )


class ViewOutputs(BaseModel):
    """The output files of one view (per-point cues appear on view 0 of their point)."""

    job_id: int
    space_id: int
    space: str
    point: int
    view: int
    outputs: dict[str, OutputLink]
