"""Gibson (`<building>/`) as downloaded: `mesh_z_up.obj` (+ .mtl and textures), +Z up, metres; no labels.
The folder's other meshes (the original-frame `mesh.obj`, navigation meshes) are not rendered."""

from __future__ import annotations

from pathlib import Path

from services.core.ingest.datasets.base import DatasetScene, first_existing

NAME = "gibson"
MESH = "mesh_z_up.obj"


def scene_mesh(folder: Path) -> Path | None:
    return first_existing(folder / MESH)


def read(mesh: Path) -> DatasetScene | None:
    if mesh.name != MESH:
        return None
    return DatasetScene(NAME, mesh.parent.name, mesh, (mesh,), up_axis="+z", unit_scale=1.0)
