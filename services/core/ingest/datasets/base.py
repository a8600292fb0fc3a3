"""What a public scan dataset's scene is made of, and the helpers its readers share.

A reader knows one dataset's layout as downloaded: which file of a scene folder to render, which files carry
its labels (and in what ids and names), the frame its files use, and which files are its traps (compressed
textures no loader here reads, a mesh that the labels do not belong to). Labels that live on another mesh
than the rendered one (a semantic mesh, a labelled copy, region meshes) are carried over by nearest
neighbour: each rendered vertex takes the labels of the closest labelled point, each face the labels most
of its vertices carry.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from services.core.ingest.labels import majority

# a rendered vertex farther than this share of the labelled mesh's bounding-box diagonal from any labelled
# point stays unlabelled (0): geometry the annotation does not cover is not given a neighbour's id
MAX_TRANSFER_FRACTION = 0.01

NYU40_NAMES = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf", "picture",
    "counter", "blinds", "desk", "shelves", "curtain", "dresser", "pillow", "mirror", "floor mat", "clothes",
    "ceiling", "books", "refridgerator", "television", "paper", "towel", "shower curtain", "box",
    "whiteboard", "person", "night stand", "toilet", "sink", "lamp", "bathtub", "bag", "otherstructure",
    "otherfurniture",
    "otherprop",
)
NYU40 = {i + 1: name for i, name in enumerate(NYU40_NAMES)}


class DatasetError(ValueError):
    """A dataset scene that cannot be used as it is, with what to do instead."""


@dataclass(frozen=True)
class SceneLabels:
    """Per rendered face: the dataset's class id and instance id, and the class names by id."""

    face_class: np.ndarray  # int32 (F,)
    face_instance: np.ndarray  # int32 (F,)
    class_names: dict[int, str]
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class DatasetScene:
    """One scene of a public dataset: the mesh to render, its frame convention and how to label it."""

    dataset: str
    scene_id: str
    mesh: Path
    files: tuple[Path, ...]  # everything the scene needs (the mesh, its materials and textures, label files)
    up_axis: str | None = None  # the dataset's up convention in source coordinates; None: detect it
    unit_scale: float | None = None  # metres per source unit; None: detect it
    source_to_world: np.ndarray | None = None  # a rigid alignment the dataset ships (ScanNet's axisAlignment)
    labeller: Callable[[trimesh.Trimesh], SceneLabels] | None = field(default=None, compare=False)

    def labels(self, mesh: trimesh.Trimesh) -> SceneLabels | None:
        """The labels of the rendered mesh as loaded (source coordinates), or None for an unlabelled
        dataset."""
        return None if self.labeller is None else self.labeller(mesh)


def read_json(path: Path) -> Any:  # json.loads; each reader checks the keys it uses
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path.name}: not readable JSON ({e})") from None
    except RecursionError:  # json's decoder recurses once per nesting level
        raise DatasetError(f"{path.name}: not readable JSON (nested too deep)") from None


def _records(data: np.ndarray | Mapping[str, ArrayLike]) -> np.ndarray:
    """A PLY element as a structured array (trimesh gives ASCII files' elements as dicts of columns)."""
    if not isinstance(data, Mapping):
        return data
    columns = {name: np.asarray(col) for name, col in data.items()}
    columns = {
        name: col[:, 0] if col.ndim == 2 and col.shape[1] == 1 else col for name, col in columns.items()
    }
    n = len(next(iter(columns.values()))) if columns else 0
    out = np.zeros(n, dtype=[(name, col.dtype, col.shape[1:]) for name, col in columns.items()])
    for name, col in columns.items():
        out[name] = col
    return out


def ply_elements(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(vertex records, face records or None) of a PLY with all its properties, as the file has them."""
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # trimesh raises many kinds on corrupt input
        raise DatasetError(f"{path.name}: could not read the PLY ({type(e).__name__}: {e})") from None
    raw = mesh.metadata.get("_ply_raw") if isinstance(mesh.metadata, dict) else None
    if not raw or "vertex" not in raw:
        raise DatasetError(f"{path.name}: not a PLY with vertices")
    face = raw["face"].get("data") if "face" in raw else None
    return _records(raw["vertex"]["data"]), None if face is None else _records(face)


def ply_with_faces(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertex records, face records) of a labelled PLY, which must have faces."""
    vertices, faces = ply_elements(path)
    if faces is None:
        raise DatasetError(f"{path.name}: has no faces")
    return vertices, faces


def segment_indices(segments_json: Path, vertices: int, mesh_name: str) -> np.ndarray:
    """The segment of each vertex (`segIndices`, ScanNet's format), checked against the mesh it indexes."""
    seg_indices = np.asarray(read_json(segments_json).get("segIndices", []), dtype=np.int64)
    if len(seg_indices) != vertices:
        raise DatasetError(
            f"{segments_json.name}: {len(seg_indices)} segIndices for the {vertices} vertices of {mesh_name}"
        )
    return seg_indices


def require_property(records: np.ndarray, name: str, path: Path) -> np.ndarray:
    if records.dtype.names is None or name not in records.dtype.names:
        raise DatasetError(
            f"{path.name}: has no '{name}' property (found {', '.join(records.dtype.names or ())})"
        )
    return np.asarray(records[name])


def xyz(records: np.ndarray) -> np.ndarray:
    return np.column_stack([np.asarray(records[c], dtype=np.float64) for c in "xyz"])


def polygons(faces: np.ndarray) -> list[np.ndarray] | np.ndarray:
    """Vertex indices of each polygon of a PLY face element: (F, k) when all have k corners, else a list."""
    indices = (
        faces["vertex_indices"] if "vertex_indices" in (faces.dtype.names or ()) else faces["vertex_index"]
    )
    if indices.dtype.names:  # (count, values) records of a fixed-length list
        indices = indices["f1"]
    if indices.dtype != object and indices.ndim == 2:
        return np.asarray(indices, dtype=np.int64)
    return [np.asarray(p, dtype=np.int64) for p in indices]


def fan(polys: list[np.ndarray] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(triangles (T, 3) of vertex indices, the polygon of each) of polygons split as fans from their first
    corner."""
    if isinstance(polys, np.ndarray):
        k = polys.shape[1]
        tris = np.concatenate([polys[:, [0, j, j + 1]] for j in range(1, k - 1)])
        return tris, np.tile(np.arange(len(polys)), k - 2)
    tris = [np.array([p[0], p[j], p[j + 1]]) for p in polys for j in range(1, len(p) - 1)]
    owner = [i for i, p in enumerate(polys) for _ in range(len(p) - 2)]
    return np.array(tris, dtype=np.int64).reshape(-1, 3), np.array(owner, dtype=np.int64)


def _pair(cls: np.ndarray, inst: np.ndarray) -> np.ndarray:
    return (cls.astype(np.int64) << 32) | (inst.astype(np.int64) & 0xFFFFFFFF)


def _unpair(pair: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (pair >> 32).astype(np.int32), (pair & 0xFFFFFFFF).astype(np.uint32).astype(np.int32)


@dataclass(frozen=True)
class LabelledSurface:
    """Triangles (T, 3, 3) in the rendered mesh's source coordinates with a (class, instance) pair each."""

    triangles: np.ndarray
    face_class: np.ndarray
    face_instance: np.ndarray

    @staticmethod
    def from_faces(vertices: np.ndarray, polys: list[np.ndarray] | np.ndarray, face_class: np.ndarray,
                   face_instance: np.ndarray) -> LabelledSurface:
        """A mesh labelled per polygon (quads and the like are split into triangles carrying its labels)."""
        tris, owner = fan(polys)
        return LabelledSurface(
            vertices[tris], np.asarray(face_class)[owner], np.asarray(face_instance)[owner]
        )

    @staticmethod
    def from_vertices(vertices: np.ndarray, polys: list[np.ndarray] | np.ndarray, vertex_class: np.ndarray,
                      vertex_instance: np.ndarray) -> LabelledSurface:
        """A mesh labelled per vertex: each triangle carries the labels most of its corners carry."""
        tris, _ = fan(polys)
        cls, inst = _unpair(majority(_pair(vertex_class, vertex_instance)[tris]))
        return LabelledSurface(vertices[tris], cls, inst)

    @staticmethod
    def of_ply_faces(vertices: np.ndarray, faces: np.ndarray, face_class: np.ndarray,
                     face_instance: np.ndarray) -> LabelledSurface:
        """A PLY's surface (vertex and face records) labelled per face."""
        return LabelledSurface.from_faces(xyz(vertices), polygons(faces), face_class, face_instance)

    @staticmethod
    def of_ply_vertices(vertices: np.ndarray, faces: np.ndarray, vertex_class: np.ndarray,
                        vertex_instance: np.ndarray) -> LabelledSurface:
        """A PLY's surface (vertex and face records) labelled per vertex."""
        return LabelledSurface.from_vertices(xyz(vertices), polygons(faces), vertex_class, vertex_instance)

    @staticmethod
    def join(parts: list[LabelledSurface]) -> LabelledSurface:
        return LabelledSurface(np.concatenate([p.triangles for p in parts]),
                               np.concatenate([p.face_class for p in parts]),
                               np.concatenate([p.face_instance for p in parts]))


CANDIDATES = 8  # labelled triangles (by nearest centroid) among which the truly closest is picked
CHUNK = 65536  # rendered faces per batch (bounds the memory of the candidate distances)


def transfer(mesh: trimesh.Trimesh, labelled: LabelledSurface) -> tuple[np.ndarray, np.ndarray]:
    """Per face of `mesh`: (class, instance) of the labelled triangle closest to its centroid.

    The candidates are the labelled triangles with the nearest centroids; of those, the one at the smallest
    point-to-triangle distance wins. A face farther than MAX_TRANSFER_FRACTION of the labelled bounding-box
    diagonal from every candidate stays 0 (unlabelled).
    """
    triangles = labelled.triangles
    corners = triangles.reshape(-1, 3)
    limit = MAX_TRANSFER_FRACTION * max(float(np.linalg.norm(np.ptp(corners, axis=0))), 1e-9)
    tree = cKDTree(triangles.mean(axis=1))
    k = min(CANDIDATES, len(triangles))
    pair_of = _pair(labelled.face_class, labelled.face_instance)
    centres = np.asarray(mesh.triangles_center)
    out = np.zeros(len(centres), dtype=np.int64)
    for start in range(0, len(centres), CHUNK):
        query = centres[start:start + CHUNK]
        _, cand = tree.query(query, k=k)
        cand = cand.reshape(len(query), k)
        points = np.repeat(query, k, axis=0)
        closest = trimesh.triangles.closest_point(triangles[cand.ravel()], points)  # type: ignore[no-untyped-call]
        distance = np.linalg.norm(closest - points, axis=1).reshape(len(query), k)
        best = np.argmin(distance, axis=1)
        rows = np.arange(len(query))
        pair = pair_of[cand[rows, best]]
        pair[distance[rows, best] > limit] = 0
        out[start:start + len(query)] = pair
    return _unpair(out)


def names_from_labels(labels: list[str]) -> dict[str, int]:
    """Class id per label string of a scene that names its classes itself: 1 + its index among the sorted
    names."""
    return {name: i + 1 for i, name in enumerate(sorted(set(labels)))}


def segment_groups(seg_indices: np.ndarray, groups: list[dict[str, Any]], class_of_label: dict[str, int],
                   path: Path, *, instance_offset: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex (class, instance) from an over-segmentation and its segGroups (ScanNet's format):
    instance = the group's objectId + `instance_offset` (0 where no group), class by its label."""
    try:
        objects = [(int(g["objectId"]), str(g["label"]), [int(s) for s in g["segments"]]) for g in groups]
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path.name}: malformed segGroups ({e})") from None
    vertex_class = np.zeros(len(seg_indices), dtype=np.int64)
    vertex_instance = np.zeros(len(seg_indices), dtype=np.int64)
    for object_id, label, segs in objects:
        member = np.isin(seg_indices, segs)
        vertex_class[member] = class_of_label.get(label, 0)
        vertex_instance[member] = object_id + instance_offset
    return vertex_class, vertex_instance


def first_existing(*candidates: Path) -> Path | None:
    return next((c for c in candidates if c.is_file()), None)
