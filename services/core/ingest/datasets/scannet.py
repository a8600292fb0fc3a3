"""ScanNet v2 (`scans/<scene>/`) as downloaded.

- `<scene>_vh_clean_2.ply`: the decimated mesh the annotations index (vertex colours) - rendered by default;
  `<scene>_vh_clean.ply` is the high-resolution mesh (rendered when named, or alone): its labels are carried
  over from the decimated one by nearest vertex.
- `<scene>_vh_clean_2.labels.ply`: the same vertices with a `label` property, the NYU40 class id (1-40).
- `<scene>_vh_clean_2.0.010000.segs.json` (`segIndices` per vertex) + `<scene>.aggregation.json` (`segGroups`:
  objectId, label, segments): instances (instance id = objectId + 1; without the labels PLY the classes are
  the file's own label strings, numbered 1.. in sorted order).
- `<scene>.txt`: `axisAlignment = m00 m01 ... m33` (row-major 4x4, metres, +Z up) aligns the scan to the
  room's walls; it becomes the space's source_to_world.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from services.core.ingest.datasets.base import (
    NYU40,
    DatasetError,
    DatasetScene,
    LabelledSurface,
    SceneLabels,
    first_existing,
    names_from_labels,
    ply_with_faces,
    read_json,
    segment_groups,
    segment_indices,
    transfer,
)

NAME = "scannet"
LOW, HIGH = "_vh_clean_2.ply", "_vh_clean.ply"


def _scene_of_mesh(mesh: Path) -> str | None:
    for suffix in (LOW, HIGH):
        if mesh.name.endswith(suffix) and mesh.name.startswith("scene"):
            return mesh.name[: -len(suffix)]
    return None


def scene_mesh(folder: Path) -> Path | None:
    """The mesh to render in a ScanNet scene folder (one scene<space>_<scan> inside), or None."""
    for suffix in (LOW, HIGH):
        found = sorted(folder.glob(f"scene*{suffix}"))
        if len(found) == 1:
            return found[0]
    return None


def axis_alignment(txt: Path) -> np.ndarray | None:
    """The 4x4 axisAlignment of a scene's meta file, or None when the file has none."""
    for line in txt.read_text(errors="replace").splitlines():
        key, _, value = line.partition("=")
        if key.strip() == "axisAlignment":
            try:
                m = np.array([float(x) for x in value.split()], dtype=np.float64)
            except ValueError:
                m = np.empty(0)
            if m.shape != (16,) or not np.isfinite(m).all():
                raise DatasetError(f"{txt.name}: axisAlignment must be 16 numbers (a row-major 4x4)")
            matrix = m.reshape(4, 4)
            rotation = matrix[:3, :3]
            if not np.allclose(matrix[3], [0, 0, 0, 1]) or not np.allclose(
                rotation @ rotation.T, np.eye(3), atol=1e-4
            ):
                raise DatasetError(f"{txt.name}: axisAlignment is not a rigid transform")
            return matrix
    return None


def _labeller(folder: Path, scene: str) -> tuple[Callable[[trimesh.Trimesh], SceneLabels] | None, list[Path]]:
    """The scene's labeller (None when it has no labels) and its label files."""
    labels_ply = folder / f"{scene}_vh_clean_2.labels.ply"
    segs = sorted(folder.glob(f"{scene}_vh_clean_2*.segs.json"))
    aggregation = first_existing(
        folder / f"{scene}.aggregation.json", folder / f"{scene}_vh_clean.aggregation.json"
    )
    points_ply = labels_ply if labels_ply.is_file() else folder / f"{scene}{LOW}"

    def label(mesh: trimesh.Trimesh) -> SceneLabels:
        vertices, faces = ply_with_faces(points_ply)
        n = len(vertices)
        vertex_class = np.zeros(n, dtype=np.int64)
        vertex_instance = np.zeros(n, dtype=np.int64)
        names: dict[int, str] = {}
        if segs and aggregation is not None:
            seg_indices = segment_indices(segs[0], n, points_ply.name)
            groups = read_json(aggregation).get("segGroups", [])
            class_of_label = names_from_labels([str(g.get("label")) for g in groups])
            vertex_class, vertex_instance = segment_groups(seg_indices, groups, class_of_label, aggregation,
                                                           instance_offset=1)  # objectId 0 is an object
            names = {i: name for name, i in class_of_label.items()}
        notes: list[str] = []
        if labels_ply.is_file() and "label" in (vertices.dtype.names or ()):
            vertex_class = np.asarray(vertices["label"], dtype=np.int64)  # NYU40: the dataset's own ids win
            names = dict(NYU40)
        elif labels_ply.is_file():
            notes.append(f"{labels_ply.name} has no 'label' property: classes from the aggregation's labels")
        if not names:
            raise DatasetError(f"ScanNet scene {scene}: no labels ({labels_ply.name}, or segs.json + "
                               "aggregation.json) beside the mesh")
        face_class, face_instance = transfer(
            mesh, LabelledSurface.of_ply_vertices(vertices, faces, vertex_class, vertex_instance))
        if len(mesh.faces) != len(faces):
            notes.append(
                f"labels carried from {points_ply.name} to the high-resolution mesh by nearest surface"
            )
        return SceneLabels(face_class, face_instance, names, tuple(notes))

    has_labels = labels_ply.is_file() or (segs and aggregation is not None)
    files = [
        p
        for p in (labels_ply, *segs[:1], aggregation, folder / f"{scene}{LOW}", folder / f"{scene}.txt")
        if p is not None and p.is_file()
    ]
    return (label if has_labels else None), files


def read(mesh: Path) -> DatasetScene | None:
    scene = _scene_of_mesh(mesh)
    if scene is None:
        return None
    folder = mesh.parent
    labeller, files = _labeller(folder, scene)
    meta = folder / f"{scene}.txt"
    alignment = axis_alignment(meta) if meta.is_file() else None
    return DatasetScene(NAME, scene, mesh, tuple(dict.fromkeys([mesh, *files])), up_axis="+z", unit_scale=1.0,
                        source_to_world=alignment, labeller=labeller)
