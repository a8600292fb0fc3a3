"""Routes for a space whose up detection could not decide: candidate side views and the person's pick.

`GET /spaces/{id}/up-candidates/{k}.png` draws candidate k (0: detection's best, 1: the runner-up) from the
side; `PUT /spaces/{id}/up` stores the chosen up with the space (its validation record and frame
columns), after which jobs plan it in that frame.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh
from fastapi import APIRouter, HTTPException, Response, status
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict, Field, field_validator
from sqlalchemy.orm import Session

from services.api.deps import ReadSessionDep, SessionDep, SettingsDep, StoreDep, TenantDep
from services.api.spaces.schemas import SpaceRead
from services.api.spaces.service import get_space
from services.core.frame_choice import record_choice
from services.core.models import Space
from services.core.settings import Settings
from services.core.space_registry import fetch_space
from services.core.spaces import SpaceError, load_space
from services.core.storage import ObjectStore
from services.core.up_preview import side_view_png

router = APIRouter(prefix="/spaces", tags=["spaces"])

SpaceId = Annotated[int, PathParam(ge=1, le=2**63 - 1, description="space id")]
CandidateIndex = Annotated[int, PathParam(ge=0, le=2, description="0: detection's best, 1: the runner-up, 2: the next")]


class UpChoice(BaseModel):
    """The up direction a person picked, in the scan's source coordinates."""

    model_config = ConfigDict(extra="forbid", strict=True)

    up: list[float] = Field(min_length=3, max_length=3, description="[x, y, z], source coordinates; any length")

    @field_validator("up")
    @classmethod
    def _finite(cls, v: list[float]) -> list[float]:
        if not np.isfinite(v).all() or float(np.linalg.norm(v)) < 1e-9:
            raise ValueError(f"up {v} must be a finite, non-zero direction [x, y, z]")
        return v


def _cache_dir(settings: Settings) -> Path:
    return Path(settings.data_dir) / "api-space-cache"


@functools.lru_cache(maxsize=8)
def _source_mesh(path: str, checksum: str) -> trimesh.Trimesh:
    """The source-frame mesh of a space file (kept for a few spaces: the two previews load it once)."""
    mesh = trimesh.load(path, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SpaceError(f"{Path(path).name}: holds no triangle mesh")
    return mesh


def _preview(store: ObjectStore, settings: Settings, space: Space, index: int) -> bytes:
    candidates = ((space.validation or {}).get("up") or {}).get("candidates") or []
    if index >= len(candidates):
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"space {space.id} has no up candidate {index}")
    path = fetch_space(store, space, _cache_dir(settings))
    return side_view_png(_source_mesh(str(path), space.checksum), np.asarray(candidates[index]["up"], dtype=float))


@router.get("/{space_id}/up-candidates/{index}.png", summary="Side view of the scan under an up candidate",
            response_class=Response, responses={200: {"content": {"image/png": {}}}})
async def up_candidate_preview(space_id: SpaceId, index: CandidateIndex, session: ReadSessionDep, store: StoreDep,
                               settings: SettingsDep, tenant: TenantDep) -> Response:
    """A small PNG: the scan seen from the side with candidate `index` pointing to the top of the picture."""
    space = get_space(session, owner=tenant, space_id=space_id)
    png = await run_in_threadpool(_preview, store, settings, space, index)
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


def _choose(session: Session, store: ObjectStore, settings: Settings, space: Space, up: list[float],
            tenant: str) -> Space:
    units = (space.validation or {}).get("units") or {}
    unit_scale: float | str = space.unit_scale if units.get("unit") == "given" else "auto"
    path = fetch_space(store, space, _cache_dir(settings))
    try:
        loaded = load_space(path, up=up, unit_scale=unit_scale)
    except SpaceError as e:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"up {up} does not work for this space: {e}") from None
    record_choice(space, loaded.up_source, loaded.source_to_world, loaded.bounds,
                  loaded.units.scale if loaded.units is not None else space.unit_scale, tenant)
    session.commit()
    return space


@router.put("/{space_id}/up", response_model=SpaceRead, summary="Pick the up direction of a space")
async def choose_up(space_id: SpaceId, body: UpChoice, session: SessionDep, store: StoreDep, settings: SettingsDep,
                    tenant: TenantDep) -> SpaceRead:
    """Store the up a person picked (source coordinates); later jobs plan the space in that frame."""
    space = get_space(session, owner=tenant, space_id=space_id)
    space = await run_in_threadpool(_choose, session, store, settings, space, body.up, tenant)
    return SpaceRead.from_row(space)
