"""A space whose up detection could not decide: side views of its candidates and the person's pick.

The pick is stored with the space (its validation record and frame columns, `ingest.frame_choice`), after
which jobs plan it in that frame. Both load the space's stored source, already validated at upload.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import trimesh
from sqlalchemy.orm import Session

from services.core.db.models import Space
from services.core.domain.errors import Invalid, NotFound
from services.core.ingest.confine import ConfinedResolver
from services.core.ingest.errors import SpaceError
from services.core.ingest.frame_choice import record_choice
from services.core.ingest.loading import load_space
from services.core.ingest.registry import fetch_space
from services.core.ingest.up_preview import side_view_png
from services.core.settings import Settings
from services.core.storage import ObjectStore


def _cache_dir(settings: Settings) -> Path:
    return Path(settings.data_dir) / "api-space-cache"


@functools.lru_cache(maxsize=8)
def _source_mesh(path: str, checksum: str) -> trimesh.Trimesh:
    """The source-frame mesh of a space file (kept for a few spaces: its previews load it once)."""
    mesh = trimesh.load(path, force="mesh", resolver=ConfinedResolver(path))  # never a file outside the scan
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SpaceError(f"{Path(path).name}: holds no triangle mesh")
    return mesh


def candidate_preview(store: ObjectStore, settings: Settings, space: Space, index: int) -> bytes:
    """PNG: the space seen from the side with its up candidate `index` at the top (NotFound past the last)."""
    candidates = ((space.validation or {}).get("up") or {}).get("candidates") or []
    if index >= len(candidates):
        raise NotFound(f"space {space.id} has no up candidate {index}")
    path = fetch_space(store, space, _cache_dir(settings))
    return side_view_png(_source_mesh(str(path), space.checksum), np.asarray(candidates[index]["up"], dtype=float))


def choose_up(session: Session, store: ObjectStore, settings: Settings, space: Space, up: list[float],
              by: str) -> Space:
    """Store `up` (source coordinates) as the space's up, with the frame it gives; Invalid when it gives none."""
    units = (space.validation or {}).get("units") or {}
    unit_scale: float | str = space.unit_scale if units.get("unit") == "given" else "auto"
    path = fetch_space(store, space, _cache_dir(settings))
    try:
        loaded = load_space(path, up=up, unit_scale=unit_scale)
    except SpaceError as e:
        raise Invalid(f"up {up} does not work for space {space.id}: {e}") from None
    record_choice(space, loaded.up_source, loaded.source_to_world, loaded.bounds,
                  loaded.units.scale if loaded.units is not None else space.unit_scale, by)
    session.commit()
    return space
