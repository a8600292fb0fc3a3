"""A space whose up detection could not decide: side views of its candidates and the person's pick.

The pick is stored with the space (its validation record and frame columns, `db.frame_choice`), after
which jobs plan it in that frame. Both load the space's stored source in the upload's limited child process
(`ingest.guard.safe_load`), never in the API process.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Unpack

import numpy as np
import trimesh
from sqlalchemy.orm import Session

from services.core.db.frame_choice import record_choice
from services.core.db.models import Space
from services.core.domain.errors import Invalid, NotFound
from services.core.domain.jobspec import SpaceFrame
from services.core.ingest.errors import SpaceError
from services.core.ingest.frame.up_preview import side_view_png
from services.core.ingest.guard.safe_load import load_space_limited
from services.core.ingest.loading import LoadedSpace
from services.core.ingest.registry import fetch_space
from services.core.settings import Settings
from services.core.storage import ObjectStore


def _cache_dir(settings: Settings) -> Path:
    return Path(settings.data_dir) / "api-space-cache"


def _limits(settings: Settings) -> tuple[int, int, float]:
    return settings.upload_max_faces, settings.upload_parse_memory_mb, settings.upload_parse_timeout_s


def _load_limited(limits: tuple[int, int, float], path: Path, **frame: Unpack[SpaceFrame]) -> LoadedSpace:
    """`load_space` in the upload's memory-, CPU- and time-limited child: never the scan's parser in the
    API."""
    max_faces, memory_mb, timeout_s = limits
    return load_space_limited(path, max_faces=max_faces, memory_mb=memory_mb, timeout_s=timeout_s, **frame)


@functools.lru_cache(maxsize=8)
def _source_mesh(
    path: str, checksum: str, source_to_world: str, limits: tuple[int, int, float]
) -> trimesh.Trimesh:
    """The source-frame mesh of a space file (kept for a few spaces: its previews load it once).

    Loaded in the limited child in the space's stored frame, then taken back to source coordinates.
    """
    loaded = _load_limited(limits, Path(path), source_to_world=json.loads(source_to_world))
    mesh = loaded.mesh.copy()
    mesh.apply_transform(np.linalg.inv(loaded.source_to_world))
    return mesh


def candidate_preview(store: ObjectStore, settings: Settings, space: Space, index: int) -> bytes:
    """PNG: the space seen from the side with its up candidate `index` at the top (NotFound past the last)."""
    candidates = ((space.validation or {}).get("up") or {}).get("candidates") or []
    if index >= len(candidates):
        raise NotFound(f"space {space.id} has no up candidate {index}")
    path = fetch_space(store, space, _cache_dir(settings))
    mesh = _source_mesh(str(path), space.checksum, json.dumps(space.source_to_world), _limits(settings))
    return side_view_png(mesh, np.asarray(candidates[index]["up"], dtype=float))


def load_choice(store: ObjectStore, settings: Settings, space: Space, up: list[float] | None,
                unit_scale: float | None = None) -> LoadedSpace:
    """The space loaded under `up` (source coordinates; None: the detected one) and `unit_scale` (None: the
    upload's, or chosen from the storey), without its mesh; Invalid when they give none (ambiguous units name
    the candidates). Needs no database session: the caller's is not held while the scan is read."""
    validation = space.validation or {}
    if up is None:
        up = [float(x) for x in (validation.get("up") or {}).get("source_direction", [0.0, 0.0, 1.0])]
    units = validation.get("units") or {}
    scale: float | str = unit_scale if unit_scale is not None else (
        space.unit_scale if units.get("unit") == "given" else "auto")
    path = fetch_space(store, space, _cache_dir(settings))
    max_faces, memory_mb, timeout_s = _limits(settings)
    try:
        return load_space_limited(path, max_faces=max_faces, memory_mb=memory_mb, timeout_s=timeout_s, up=up,
                                  unit_scale=scale, accept_up_guess=False, keep_mesh=False)
    except SpaceError as e:
        raise Invalid(f"up {up} does not work for space {space.id}: {e}") from None


def record_up(session: Session, space: Space, loaded: LoadedSpace, by: str) -> Space:
    """Store the frame of `loaded` (from load_choice) as the space's, picked by `by`."""
    record_choice(space, loaded.up_source, loaded.source_to_world, loaded.bounds,
                  loaded.units.scale if loaded.units is not None else space.unit_scale, by)
    session.commit()
    return space
