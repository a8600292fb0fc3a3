"""ScanNet++ (`data/<scene>/scans/`) as downloaded.

- `mesh_aligned_0.05.ply`: the scan, aligned (+Z up, metres), vertex colours - rendered.
- `segments.json` (`segIndices` per vertex of that mesh) + `segments_anno.json` (`segGroups`: objectId,
  already 1-based, label, segments): instances and classes. `mesh_aligned_0.05_semantic.ply` is the same mesh
  coloured by class for viewing; its colours carry no ids, so the JSON files are what is read.
- Class ids: 1 + the line index of the label in the release's `metadata/semantic_classes.txt` when it sits at
  the dataset root, else 1.. over the scene's own sorted label names (names recorded per space either way).
"""

from __future__ import annotations

from pathlib import Path

import trimesh

from services.core.ingest.datasets.base import (
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

NAME = "scannetpp"
MESH = "mesh_aligned_0.05.ply"
SEMANTIC_MESH = "mesh_aligned_0.05_semantic.ply"


def scene_mesh(folder: Path) -> Path | None:
    return first_existing(folder / "scans" / MESH, folder / MESH)


def _dataset_classes(scans: Path) -> dict[str, int] | None:
    """Class id per name from the release's metadata/semantic_classes.txt above the scene, when present."""
    for root in list(scans.parents)[:4]:
        listing = root / "metadata" / "semantic_classes.txt"
        if listing.is_file():
            names = [
                line.strip() for line in listing.read_text(errors="replace").splitlines() if line.strip()
            ]
            return {name: i + 1 for i, name in enumerate(names)}
    return None


def read(mesh: Path) -> DatasetScene | None:
    if mesh.name != MESH:
        return None
    scans = mesh.parent
    scene_id = scans.parent.name if scans.name == "scans" else scans.name
    segments, annotation = scans / "segments.json", scans / "segments_anno.json"

    def label(loaded: trimesh.Trimesh) -> SceneLabels:
        vertices, faces = ply_with_faces(mesh)
        seg_indices = segment_indices(segments, len(vertices), MESH)
        groups = read_json(annotation).get("segGroups", [])
        labels = [str(g.get("label")) for g in groups]
        classes = _dataset_classes(scans)
        notes: tuple[str, ...] = ()
        if classes is None:
            classes = names_from_labels(labels)
        elif missing := sorted(set(labels) - set(classes)):
            notes = (
                f"labels not in metadata/semantic_classes.txt stay unlabelled: {', '.join(missing[:10])}",
            )
        vertex_class, vertex_instance = segment_groups(seg_indices, groups, classes, annotation)
        face_class, face_instance = transfer(
            loaded, LabelledSurface.of_ply_vertices(vertices, faces, vertex_class, vertex_instance))
        used = set(labels)
        return SceneLabels(face_class, face_instance, {i: n for n, i in classes.items() if n in used}, notes)

    labelled = segments.is_file() and annotation.is_file()
    files = [p for p in (mesh, segments, annotation, scans / SEMANTIC_MESH) if p.is_file()]
    return DatasetScene(NAME, scene_id, mesh, tuple(files), up_axis="+z", unit_scale=1.0,
                        labeller=label if labelled else None)
