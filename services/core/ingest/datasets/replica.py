"""Replica (`<scene>/`, e.g. room_0) as downloaded.

- `mesh.ply`: the scan as quads with vertex colours - rendered (trimesh splits each quad in two).
- `habitat/mesh_semantic.ply`: the same surfaces with a face property `object_id`, and
  `habitat/info_semantic.json`: `id_to_label` (class id per object id, -1 = none) and `classes` ([{id,
  name}]). Instance id = object_id, class id = id_to_label[object_id]; both are Replica's own.
- Metres; up is detected (the scenes are not all stored the same way up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from services.core.ingest.datasets.base import (
    DatasetError,
    DatasetScene,
    LabelledSurface,
    SceneLabels,
    ply_with_faces,
    read_json,
    require_property,
    transfer,
)

NAME = "replica"


def scene_mesh(folder: Path) -> Path | None:
    mesh = folder / "mesh.ply"
    return mesh if mesh.is_file() and (folder / "habitat" / "mesh_semantic.ply").is_file() else None


def read(mesh: Path) -> DatasetScene | None:
    folder = mesh.parent
    semantic, info = folder / "habitat" / "mesh_semantic.ply", folder / "habitat" / "info_semantic.json"
    if mesh.name != "mesh.ply" or not semantic.is_file():
        return None

    def label(loaded: trimesh.Trimesh) -> SceneLabels:
        doc = read_json(info)
        try:
            id_to_label = np.asarray(doc["id_to_label"], dtype=np.int64)
            names = {int(c["id"]): str(c["name"]) for c in doc.get("classes", [])}
        except (KeyError, TypeError, ValueError) as e:
            raise DatasetError(f"{info.name}: expected id_to_label and classes ({e})") from None
        vertices, faces = ply_with_faces(semantic)
        object_id = require_property(faces, "object_id", semantic).astype(np.int64)
        known = (object_id >= 0) & (object_id < len(id_to_label))
        face_class = np.where(known, id_to_label[np.clip(object_id, 0, len(id_to_label) - 1)], 0)
        surface = LabelledSurface.of_ply_faces(
            vertices, faces, np.maximum(face_class, 0), np.maximum(object_id, 0)
        )
        cls, inst = transfer(loaded, surface)
        return SceneLabels(cls, inst, names)

    files = [p for p in (mesh, semantic, info) if p.is_file()]
    return DatasetScene(NAME, folder.name, mesh, tuple(files), unit_scale=1.0,
                        labeller=label if info.is_file() else None)
