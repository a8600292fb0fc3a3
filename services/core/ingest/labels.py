"""Per-face semantic labels of a scan, in the order of trimesh's triangles.

Labels come from PLY face properties `class_id` and `instance_id` (Replica's `object_id` is accepted as the
instance, Matterport3D's `category_id` and `segment_id` as class and instance). They are read from the raw
PLY elements trimesh keeps in `mesh.metadata['_ply_raw']` and mapped onto the triangles the way trimesh
triangulates polygons (triangles, then first and second halves of quads, then fans); that mapping is
verified on the vertex positions, because a wrong guess would label the wrong faces silently. A
Replica-style `info_semantic.json` (`id_to_label`) beside the mesh supplies classes when only object ids
are present. ScanNet's per-vertex segment files (`services.core.ingest.formats`) are mapped to triangles by
the majority of each triangle's vertices.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from services.core.ingest.errors import SpaceError
from services.core.ingest.formats import ScanFormatError, scannet_vertex_labels
from services.core.ingest.guard.confine import ReferenceRefused, read_confined

# Replica: class_id + object_id; Matterport3D region/house PLYs: category_id + segment_id
_CLASS_FIELDS = ("class_id", "category_id")


_INSTANCE_FIELDS = ("instance_id", "object_id", "segment_id")


def _field(data: object, name: str) -> np.ndarray | None:
    try:
        if isinstance(data, dict):
            return np.asarray(data[name]) if name in data else None
        if isinstance(data, np.ndarray) and data.dtype.names and name in data.dtype.names:
            col = data[name]
            if col.dtype.names:  # list properties come as (count, values) records
                col = col["f1"]
            return np.asarray(col)
    except (KeyError, ValueError, TypeError):
        return None
    return None


def _polygon_lengths(face_data: object, n_faces: int) -> list[np.ndarray] | np.ndarray | None:
    for name in ("vertex_indices", "vertex_index"):
        idx = _field(face_data, name)
        if idx is None:
            continue
        if idx.dtype != object and idx.ndim == 2 and len(idx) == n_faces:
            return idx
        return [np.asarray(i) for i in idx]
    return None


def _triangle_to_polygon(polys: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Raw PLY face index of each triangle, in trimesh's triangulation order (geometry.triangulate_quads)."""
    if isinstance(polys, np.ndarray):
        n, k = polys.shape
        if k == 3:
            return np.arange(n)
        if k == 4:
            return np.concatenate([np.arange(n), np.arange(n)])
        lengths = np.full(n, k)
    else:
        lengths = np.array([len(p) for p in polys])
    ids = np.arange(len(lengths))
    tri, quad, poly = ids[lengths == 3], ids[lengths == 4], ids[lengths > 4]
    return np.concatenate([tri, quad, quad, np.repeat(poly, lengths[poly] - 2)]).astype(np.int64)


def _ply_triangle_polygons(
    mesh: trimesh.Trimesh, notes: list[str]
) -> tuple[object, np.ndarray, np.ndarray] | None:
    """(raw PLY face data, padded polygon vertex indices, raw polygon of each triangle), verified on
    positions."""
    raw = mesh.metadata.get("_ply_raw") if isinstance(mesh.metadata, dict) else None
    data = raw["face"].get("data") if raw and "face" in raw else None
    if raw is None or data is None:
        return None
    n_raw = len(data)
    polys = _polygon_lengths(data, n_raw)
    if polys is None:
        notes.append("PLY face labels ignored: faces have no vertex_indices property")
        return None
    tri_to_poly = _triangle_to_polygon(polys)
    if len(tri_to_poly) != len(mesh.faces):
        notes.append(
            f"PLY face labels ignored: {len(tri_to_poly)} triangles expected from {n_raw} polygons, "
            f"trimesh made {len(mesh.faces)}"
        )
        return None
    # verify on positions: each triangle's first vertex must be a vertex of its polygon
    vdata: Any = raw["vertex"].get("data") if "vertex" in raw else None  # trimesh's raw PLY data: untyped
    padded = polys
    try:
        raw_xyz = np.column_stack([np.asarray(vdata[c], dtype=np.float64) for c in "xyz"])
        first = mesh.vertices[mesh.faces[:, 0]]
        if not isinstance(polys, np.ndarray):  # ragged polygons: pad with a repeat of their first vertex
            kmax = max(len(p) for p in polys)
            padded = np.array([np.pad(p, (0, kmax - len(p)), mode="edge") for p in polys])
        cand = raw_xyz[padded[tri_to_poly]]  # (F, k, 3)
        tol = 1e-6 * max(float(mesh.scale), 1e-9)  # trimesh merges vertices closer than ~1e-8
        ok = np.isclose(cand, first[:, None, :], rtol=0, atol=tol).all(axis=2).any(axis=1)
    except (KeyError, TypeError, ValueError, IndexError):
        ok = np.zeros(1, dtype=bool)
    if not ok.all():
        notes.append("PLY face labels ignored: could not align them with trimesh's triangles")
        return None
    return data, np.asarray(padded), tri_to_poly


def read_ply_semantics(
    mesh: trimesh.Trimesh, source: Path
) -> tuple[np.ndarray | None, np.ndarray | None, list[str]]:
    notes: list[str] = []
    raw = mesh.metadata.get("_ply_raw") if isinstance(mesh.metadata, dict) else None
    data = raw["face"].get("data") if raw and "face" in raw else None
    cls = next((c for c in (_field(data, f) for f in _CLASS_FIELDS) if c is not None), None)
    inst = next((c for c in (_field(data, f) for f in _INSTANCE_FIELDS) if c is not None), None)
    if cls is None and inst is None:
        return None, None, notes
    table = _ply_triangle_polygons(mesh, notes)
    if table is None:
        return None, None, notes
    tri_to_poly = table[2]
    face_class = cls[tri_to_poly].astype(np.int32) if cls is not None else None
    face_instance = inst[tri_to_poly].astype(np.int32) if inst is not None else None
    if face_class is None and face_instance is not None:
        face_class = _classes_from_info_semantic(source, face_instance, notes)
    return face_class, face_instance, notes


def majority(labels: np.ndarray) -> np.ndarray:
    """Per row of (F, k) vertex labels: the label most of its vertices carry (ties: the first vertex's)."""
    best = labels[:, 0].copy()
    best_count = (labels == best[:, None]).sum(axis=1)
    for j in range(1, labels.shape[1]):
        count = (labels == labels[:, j:j + 1]).sum(axis=1)
        better = count > best_count
        best[better], best_count[better] = labels[better, j], count[better]
    return best


def scannet_labels(
    mesh: trimesh.Trimesh, source: Path
) -> tuple[np.ndarray, np.ndarray, dict[int, str], list[str]] | None:
    """Per-triangle (class, instance, class names, notes) of a ScanNet `*_vh_clean_2.ply`, or None."""
    notes: list[str] = []
    raw = mesh.metadata.get("_ply_raw") if isinstance(mesh.metadata, dict) else None
    if not raw or "vertex" not in raw:
        return None
    try:
        found = scannet_vertex_labels(source, len(raw["vertex"]["data"]))
    except ScanFormatError as e:
        raise SpaceError(str(e)) from None
    if found is None:
        return None
    vertex_class, vertex_instance, names = found
    table = _ply_triangle_polygons(mesh, notes)
    if table is None:
        raise SpaceError(
            f"{source.name}: ScanNet labels found but the faces could not be matched: {'; '.join(notes)}"
        )
    _, polys, tri_to_poly = table
    poly_class = majority(vertex_class[polys])
    poly_instance = majority(vertex_instance[polys])
    return poly_class[tri_to_poly].astype(np.int32), poly_instance[tri_to_poly].astype(np.int32), names, notes


def _classes_from_info_semantic(
    source: Path, face_instance: np.ndarray, notes: list[str]
) -> np.ndarray | None:
    for cand in (source.parent / "info_semantic.json", source.parent / "habitat" / "info_semantic.json"):
        if not cand.is_file():
            continue
        try:
            id_to_label = np.asarray(json.loads(read_confined(cand, source))["id_to_label"], dtype=np.int64)
        except ReferenceRefused as e:
            raise SpaceError(f"{source.name}: {e}") from None
        except (OSError, ValueError, KeyError, TypeError) as e:
            notes.append(f"{cand.name} unreadable ({e}); no class labels")
            return None
        inst = face_instance.astype(np.int64)
        valid = (inst >= 0) & (inst < len(id_to_label))
        out = np.zeros(len(inst), dtype=np.int32)
        out[valid] = np.maximum(id_to_label[inst[valid]], 0)
        return out
    return None
