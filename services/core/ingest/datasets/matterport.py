"""Matterport3D (`v1/scans/<house>/`, its zips unpacked there) as downloaded.

- `matterport_mesh/<uuid>/<uuid>.obj` (+ .mtl and `<uuid>_*.jpg` textures): the textured house - rendered.
- `region_segmentations/region<N>.ply`: the house cut into regions, faces with `material_id`, `segment_id` and
  `category_id`; `region<N>.semseg.json` groups segments into objects (segGroups: objectId, segments).
- `house_segmentations/<house>.house`: `C category_index category_mapping_index category_mapping_name
  mpcat40_index mpcat40_name 0 0 0 0 0` lines map a face's category_id to mpcat40, the class set the
  dataset's benchmarks use: class id = mpcat40 index, named by mpcat40 name (without the .house file: the
  raw category_id). Instance id = 1.. over (region, object) pairs (region, segment without semseg.json).
- The zips unpack as `<house>/<house>/...`; both that and `<house>/...` are found. +Z up, metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from services.core.ingest.datasets.base import (
    DatasetScene,
    LabelledSurface,
    SceneLabels,
    ply_elements,
    read_json,
    require_property,
    transfer,
)

NAME = "matterport3d"


def _house_root(folder: Path) -> Path | None:
    if (folder / "matterport_mesh").is_dir():
        return folder
    nested = [p.parent for p in folder.glob("*/matterport_mesh") if p.is_dir()]
    return nested[0] if len(nested) == 1 else None


def scene_mesh(folder: Path) -> Path | None:
    root = _house_root(folder)
    meshes = sorted((root / "matterport_mesh").glob("*/*.obj")) if root is not None else []
    return meshes[0] if len(meshes) == 1 else None


def read_house_categories(house: Path) -> dict[int, tuple[int, str]]:
    """category_index -> (mpcat40 index, mpcat40 name) from a .house file's C lines."""
    out: dict[int, tuple[int, str]] = {}
    for line in house.read_text(errors="replace").splitlines():
        tokens = line.split()
        if len(tokens) >= 8 and tokens[0] == "C":
            try:
                out[int(tokens[1])] = (int(tokens[-7]), tokens[-6])
            except ValueError:
                continue
    return out


def _region_objects(region_ply: Path, segment_id: np.ndarray) -> np.ndarray:
    """Object id per face of a region: from its semseg.json groups, else its segment id (+1; 0 = none)."""
    semseg = region_ply.with_suffix(".semseg.json")
    if not semseg.is_file():
        return np.where(segment_id >= 0, segment_id + 1, 0)
    out = np.zeros(len(segment_id), dtype=np.int64)
    for g in read_json(semseg).get("segGroups", []):
        out[np.isin(segment_id, [int(s) for s in g.get("segments", [])])] = int(g.get("objectId", -1)) + 1
    return out


def read(mesh: Path) -> DatasetScene | None:
    if mesh.suffix.lower() != ".obj" or mesh.parent.parent.name != "matterport_mesh":
        return None
    root = mesh.parent.parent.parent
    house_id = root.name
    regions = sorted((root / "region_segmentations").glob("region*.ply"))
    house = root / "house_segmentations" / f"{house_id}.house"

    def label(loaded: trimesh.Trimesh) -> SceneLabels:
        categories = read_house_categories(house) if house.is_file() else {}
        surfaces, classes = [], []
        next_instance = 0
        for region in regions:
            vertices, faces = ply_elements(region)
            if faces is None:
                continue
            category = require_property(faces, "category_id", region).astype(np.int64)
            objects = _region_objects(region, require_property(faces, "segment_id", region).astype(np.int64))
            if categories:
                category = np.array([categories.get(int(c), (0, ""))[0] for c in category], dtype=np.int64)
            _, local = np.unique(objects, return_inverse=True)
            instances = np.where(objects > 0, local + 1 + next_instance, 0)
            next_instance += int(local.max()) + 1 if len(local) else 0
            classes.append(np.maximum(category, 0))
            surfaces.append(LabelledSurface.of_ply_faces(vertices, faces, classes[-1], instances))
        cls, inst = transfer(loaded, LabelledSurface.join(surfaces))
        if categories:
            names = {index: name for index, name in categories.values() if index > 0}
        else:
            names = {int(c): f"category {int(c)}" for c in np.unique(np.concatenate(classes)) if c > 0}
        return SceneLabels(cls, inst, names)

    files = [mesh, *regions, *(r.with_suffix(".semseg.json") for r in regions
                                if r.with_suffix(".semseg.json").is_file())]
    if house.is_file():
        files.append(house)
    return DatasetScene(NAME, house_id, mesh, tuple(files), up_axis="+z", unit_scale=1.0,
                        labeller=label if regions else None)
