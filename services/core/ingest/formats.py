"""Label files of the public scan datasets that sit beside the mesh (the mesh itself is a plain PLY).

ScanNet: `<scene>_vh_clean_2.ply` (vertex colours) with `<scene>_vh_clean_2.0.010000.segs.json`
(`segIndices`: an over-segmentation id per PLY vertex) and `<scene>.aggregation.json` (or
`<scene>_vh_clean.aggregation.json`; `segGroups`: objects, each a list of segments and a label
string). Instance id = objectId + 1 and class id = 1 + the index of the object's label among the
file's own sorted label names (0 = unlabelled for both), so every scene names its classes itself;
the names are recorded per space in job.json.

Matterport3D region/house PLYs carry labels as face properties (`category_id`, `segment_id`) and
Replica as `class_id`/`object_id`; those are read in `services.core.ingest.loading`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.core.ingest.guard.confine import read_confined

SCANNET_MESH_SUFFIX = "_vh_clean_2.ply"


class ScanFormatError(ValueError):
    """A dataset label file that is present but unusable, with a message for the user."""


def _scene_id(mesh_path: Path) -> str | None:
    name = mesh_path.name
    return name[: -len(SCANNET_MESH_SUFFIX)] if name.endswith(SCANNET_MESH_SUFFIX) else None


def scannet_companions(mesh_path: Path) -> tuple[Path, Path] | None:
    """(segs.json, aggregation.json) beside a ScanNet mesh, or None when it is not one."""
    scene = _scene_id(mesh_path)
    if scene is None:
        return None
    folder = mesh_path.parent
    segs = sorted(folder.glob(f"{scene}_vh_clean_2*.segs.json"))
    aggs = [p for p in (folder / f"{scene}.aggregation.json", folder / f"{scene}_vh_clean.aggregation.json")
            if p.is_file()]
    if not segs or not aggs:
        return None
    return segs[0], aggs[0]


def _read_json(path: Path, mesh_path: Path) -> dict:
    try:
        doc = json.loads(read_confined(path, mesh_path))  # never through a link out of the scan's folder
    except (OSError, ValueError) as e:
        raise ScanFormatError(f"{path.name}: not readable JSON ({e})") from None
    except RecursionError:  # json's decoder recurses once per nesting level
        raise ScanFormatError(f"{path.name}: not readable JSON (nested too deep)") from None
    if not isinstance(doc, dict):
        raise ScanFormatError(f"{path.name}: expected a JSON object")
    return doc


def scannet_vertex_labels(
    mesh_path: Path, n_vertices: int
) -> tuple[np.ndarray, np.ndarray, dict[int, str]] | None:
    """Per raw PLY vertex (class id, instance id) and the class names, or None when not a ScanNet scene."""
    found = scannet_companions(mesh_path)
    if found is None:
        return None
    segs_path, agg_path = found
    try:
        seg_of_vertex = np.asarray(_read_json(segs_path, mesh_path)["segIndices"], dtype=np.int64)
        groups = _read_json(agg_path, mesh_path)["segGroups"]
        objects = [(int(g["objectId"]), str(g["label"]), [int(s) for s in g["segments"]]) for g in groups]
    except (KeyError, TypeError, ValueError) as e:
        raise ScanFormatError(
            f"{segs_path.name} / {agg_path.name}: missing or malformed field ({e})"
        ) from None
    if len(seg_of_vertex) != n_vertices:
        raise ScanFormatError(
            f"{segs_path.name}: {len(seg_of_vertex)} segIndices for the {n_vertices} vertices of "
            f"{mesh_path.name}"
        )
    names = sorted({label for _, label, _ in objects})
    class_of_label = {label: i + 1 for i, label in enumerate(names)}
    segments = np.unique(seg_of_vertex)
    seg_class = np.zeros(len(segments), dtype=np.int32)
    seg_instance = np.zeros(len(segments), dtype=np.int32)
    for object_id, label, segs in objects:
        idx = np.searchsorted(segments, segs)
        valid = (idx < len(segments)) & (segments[np.minimum(idx, len(segments) - 1)] == segs)
        seg_class[idx[valid]] = class_of_label[label]
        seg_instance[idx[valid]] = object_id + 1
    where = np.searchsorted(segments, seg_of_vertex)
    return seg_class[where], seg_instance[where], {i + 1: n for i, n in enumerate(names)}
