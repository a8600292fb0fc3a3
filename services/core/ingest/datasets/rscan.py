"""3RScan (`<scan id>/`) as downloaded.

- `mesh.refined.v2.obj` (+ `mesh.refined.mtl`, `mesh.refined_0.png`): the textured scan - rendered.
- `labels.instances.annotated.v2.ply`: the scan's vertices with `objectId`, `globalId`, `NYU40`, `Eigen13`
  and `RIO27` per vertex. Instance id = objectId; class id = NYU40 (names: NYU40's), the one of its class
  sets that fits an 8-bit segment_semantic (globalId runs past 255).
- `semseg.v2.json`: segGroups (objectId, label) over the segments: the same objects; packed with the scene.
- Metres; up is detected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from services.core.ingest.datasets.base import (
    NYU40,
    DatasetScene,
    LabelledSurface,
    SceneLabels,
    first_existing,
    ply_with_faces,
    require_property,
    transfer,
)

NAME = "3rscan"
MESH = "mesh.refined.v2.obj"
LABELS = "labels.instances.annotated.v2.ply"


def scene_mesh(folder: Path) -> Path | None:
    return first_existing(folder / MESH)


def read(mesh: Path) -> DatasetScene | None:
    if mesh.name != MESH:
        return None
    folder = mesh.parent
    labels_ply, semseg = folder / LABELS, folder / "semseg.v2.json"

    def label(loaded: trimesh.Trimesh) -> SceneLabels:
        vertices, faces = ply_with_faces(labels_ply)
        object_id = require_property(vertices, "objectId", labels_ply).astype(np.int64)
        nyu40 = require_property(vertices, "NYU40", labels_ply).astype(np.int64)
        cls, inst = transfer(loaded, LabelledSurface.of_ply_vertices(vertices, faces, nyu40, object_id))
        return SceneLabels(cls, inst, dict(NYU40))

    files = [p for p in (mesh, labels_ply, semseg) if p.is_file()]
    return DatasetScene(NAME, folder.name, mesh, tuple(files), unit_scale=1.0,
                        labeller=label if labels_ply.is_file() else None)
