"""Loading a space (a scanned mesh) into the world frame shared by planning and rendering.

The planner and the worker both call `load_space`, so the pixels the worker renders line up with the
poses the planner chose. Frames and units:

- *source frame*: the coordinates `trimesh.load(source, force="mesh")` gives for the file, in the
  file's units. Its face order is the reference for the `fragments` cue (DESIGN.md section 5).
- *world frame*: metres, +Z up. `source_to_world` (4x4) = uniform scale `unit_scale` (metres per
  source unit) followed by the rotation that takes the up direction to +Z, with **no translation**
  (heights are measured from detected floors by the planner, not from z = 0), unless the user gives a
  whole `source_to_world` (rotation, uniform scale and translation), which is used as it is.

Up is given (`up_axis` name or `up` vector in source coordinates) or detected in any orientation
(`services.core.gravity`: plane families of the face normals, then the floor, a support base or the
file convention); units are given or chosen from the storey height of rooms. How, and how sure, is
kept in `LoadedSpace.frame_record()` for job.json. Point clouds (.xyz, .pts, PLY without faces) are
meshed first (`services.core.pointcloud`); that mesh's faces are then the `fragments` reference.

Semantic labels come from PLY face properties `class_id` and `instance_id` (Replica's `object_id` is
accepted as the instance, Matterport3D's `category_id` and `segment_id` as class and instance). They are
read from the raw PLY elements trimesh keeps in `mesh.metadata['_ply_raw']` and mapped onto the triangles
the way trimesh triangulates polygons (triangles, then first and second halves of quads, then fans), and
that mapping is verified on the vertex positions. A Replica-style `info_semantic.json` (`id_to_label`)
beside the mesh supplies classes when only object ids are present. ScanNet's per-vertex segment files
(`services.core.scan_formats`) are mapped to triangles by the majority of each triangle's vertices.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import stat
import tempfile
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import trimesh

from services.core.gravity import (
    UnitChoice,
    UnitError,
    UpEstimate,
    axis_vector,
    choose_unit_scale,
    estimate_up,
    floor_evidence,
)
from services.core.ingest.datasets import DatasetError, DatasetScene, scene_mesh_in, scene_of
from services.core.jobspec import UP_AXES, similarity_scale
from services.core.pointcloud import (
    CLOUD_SUFFIXES,
    CloudError,
    cloud_from_ply,
    mesh_cloud_cached,
    read_text_cloud,
)
from services.core.scan_formats import SCANNET_MESH_SUFFIX, ScanFormatError, scannet_vertex_labels
from services.core.storage.base import sha256_file

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", *CLOUD_SUFFIXES)

MAX_EXTENT_M = 10_000.0  # a 10 km scan means the units are wrong
MIN_EXTENT_M = 0.001  # everything inside 1 mm: same
ZIP_MAX_TOTAL_BYTES = 8 * 1024**3  # uncompressed size of all members
ZIP_MAX_RATIO = 200.0  # uncompressed / compressed, per member and in total
ZIP_MAX_MEMBERS = 20_000


class SpaceError(ValueError):
    """A space that cannot be used, with a message meant for the user who uploaded it."""


@dataclass(frozen=True, eq=False)
class LoadedSpace:
    """A space in the world frame (metres, +Z up) plus what the planner and worker need to know."""

    mesh: trimesh.Trimesh  # world frame; faces in the order of trimesh.load(source, force="mesh")
    source_path: Path  # the mesh file that was loaded (a zip's path when extracted to a temporary folder)
    source_to_world: np.ndarray  # 4x4: source coordinates -> world metres (+Z up); translation only when given
    has_texture: bool  # UV coordinates and a texture image
    has_vertex_colors: bool
    face_class: np.ndarray | None  # int32 class id per face
    face_instance: np.ndarray | None  # int32 instance id per face
    has_semantics: bool  # both class and instance ids per face
    bounds: np.ndarray  # (2, 3) world-frame AABB, metres
    checksum: str  # sha256 hex of the mesh file
    face_count: int
    up_source: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # up, source frame
    up_method: str = "given"  # given | floor | base | convention | convention-tie | source_to_world
    warnings: tuple[str, ...] = ()
    up_estimate: UpEstimate | None = None  # how up was found and how sure
    units: UnitChoice | None = None  # the unit scale and why
    reconstruction: dict[str, Any] | None = None  # point clouds: how they were meshed
    class_names: dict[int, str] | None = None  # class id -> name, when the file names its classes

    def frame_record(self) -> dict[str, Any]:
        """What was detected about the frame, for job.json and `omnidata plan` (JSON-ready)."""
        scale = self.units.scale if self.units is not None else float(np.cbrt(np.linalg.det(self.source_to_world[:3, :3])))
        est = self.up_estimate or UpEstimate(self.up_source, self.up_method)
        out: dict[str, Any] = {"up": est.record(scale)}
        if self.units is not None:
            out["units"] = self.units.record()
        if self.reconstruction is not None:
            out["reconstruction"] = self.reconstruction
        if self.class_names:
            out["class_names"] = {str(k): v for k, v in sorted(self.class_names.items())}
        return out

    def frame_summary(self) -> str:
        """One line: up, method, confidence and units (printed by `omnidata plan`)."""
        rec = self.frame_record()
        up = rec["up"]
        direction = ", ".join(f"{x:.4g}" for x in up["source_direction"])
        line = f"up [{direction}] ({up['method']}, {up['confidence']} confidence"
        if up["floor_area_m2"]:
            line += f", floor {up['floor_area_m2']:.3g} m2"
        if up["runner_up_angle_deg"] is not None:
            line += f", runner-up {up['runner_up_angle_deg']:.0f} deg away"
        line += ")"
        if "units" in rec:
            line += f"; units: {rec['units']['unit']} x{rec['units']['unit_scale']:g} ({rec['units']['reason']})"
        return line


FRAME_KEYS = ("up", "units", "reconstruction", "class_names", "valid_fraction")


def frame_of(record: dict[str, Any] | None) -> dict[str, Any] | None:
    """The frame part of a space record (validation, plan summary): what the API shows; None when absent."""
    if not record:
        return None
    return {k: record[k] for k in FRAME_KEYS if k in record} or None


# ---------------------------------------------------------------------------------------------
# finding the mesh: file, folder or zip


def _is_hidden(p: Path) -> bool:
    return any(part.startswith(".") or part == "__MACOSX" for part in p.parts)


def _meshes_in(folder: Path) -> list[Path]:
    found = [
        p for p in sorted(folder.rglob("*"))
        if p.is_file() and p.suffix.lower() in MESH_SUFFIXES and not _is_hidden(p.relative_to(folder))
    ]
    return found


def safe_extract_zip(
    zip_path: Path,
    dest: Path,
    *,
    max_total_bytes: int = ZIP_MAX_TOTAL_BYTES,
    max_ratio: float = ZIP_MAX_RATIO,
    max_members: int = ZIP_MAX_MEMBERS,
) -> None:
    """Extract `zip_path` into `dest`, refusing traversal, absolute paths, links and zip bombs (SpaceError)."""
    name = zip_path.name
    try:
        zf = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise SpaceError(f"{name}: not a readable zip archive ({e})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise SpaceError(f"{name}: {len(infos)} members in the archive, more than the limit {max_members}")
        total = 0
        total_compressed = 0
        for info in infos:
            raw = info.filename
            member = raw.replace("\\", "/")
            pure = PurePosixPath(member)
            if member.startswith("/") or (len(member) > 1 and member[1] == ":"):
                raise SpaceError(f"{name}: member {raw!r} has an absolute path; refusing to extract")
            if ".." in pure.parts:
                raise SpaceError(f"{name}: member {raw!r} climbs out of the archive ('..'); refusing to extract")
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise SpaceError(f"{name}: member {raw!r} is a symbolic link; refusing to extract")
            if info.flag_bits & 0x1:
                raise SpaceError(f"{name}: member {raw!r} is encrypted")
            total += info.file_size
            total_compressed += info.compress_size
            if info.file_size > 1_000_000 and info.file_size > max_ratio * max(info.compress_size, 1):
                raise SpaceError(
                    f"{name}: member {raw!r} expands {info.file_size / max(info.compress_size, 1):.0f}x "
                    f"(limit {max_ratio:.0f}x): refusing a possible zip bomb"
                )
        if total > max_total_bytes:
            raise SpaceError(
                f"{name}: uncompressed size {total} bytes exceeds the limit {max_total_bytes}: "
                "refusing a possible zip bomb"
            )
        if total > 1_000_000 and total > max_ratio * max(total_compressed, 1):
            raise SpaceError(
                f"{name}: archive expands {total / max(total_compressed, 1):.0f}x (limit {max_ratio:.0f}x): "
                "refusing a possible zip bomb"
            )
        dest = dest.resolve()
        dest.mkdir(parents=True, exist_ok=True)
        written = 0
        for info in infos:
            member = info.filename.replace("\\", "/")
            target = (dest / member).resolve()
            if dest != target and dest not in target.parents:
                raise SpaceError(f"{name}: member {info.filename!r} escapes the extraction folder")
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            # stream with our own count: the sizes in the headers can lie
            try:
                with zf.open(info) as src, open(target, "wb") as out:
                    member_bytes = 0
                    while chunk := src.read(1 << 20):
                        member_bytes += len(chunk)
                        written += len(chunk)
                        if member_bytes > info.file_size or written > max_total_bytes:
                            raise SpaceError(
                                f"{name}: member {info.filename!r} inflates past its declared size: "
                                "refusing a possible zip bomb"
                            )
                        out.write(chunk)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, ValueError) as e:
                # bad CRC, corrupt deflate stream, cut-off member, unknown compression method
                raise SpaceError(f"{name}: member {info.filename!r} is corrupt ({e}); re-create the archive") from None


def resolve_source(
    path: str | Path,
    extract_dir: str | Path | None = None,
    **zip_limits: Any,
) -> Path:
    """The one mesh file of a space: the file itself, the only mesh in a folder, or in a zip.

    A zip is extracted safely (see `safe_extract_zip`) into `extract_dir`, or into a new temporary
    folder that the caller owns when `extract_dir` is None.
    """
    p = Path(path)
    if not p.exists():
        raise SpaceError(f"{p}: no such file or folder")
    if p.is_file() and p.suffix.lower() == ".zip":
        dest = Path(extract_dir) if extract_dir is not None else Path(tempfile.mkdtemp(prefix="omnidata-space-"))
        safe_extract_zip(p, dest, **zip_limits)
        return _one_mesh(dest, f"archive {p.name}")
    if p.is_file():
        if p.suffix.lower() not in MESH_SUFFIXES:
            raise SpaceError(
                f"{p.name}: unsupported file type {p.suffix or '(none)'!r}; "
                f"use one of {', '.join(MESH_SUFFIXES)} or a folder/.zip holding one"
            )
        return p
    if p.is_dir():
        return _one_mesh(p, f"folder {p}")
    raise SpaceError(f"{p}: not a file or folder")


def _one_mesh(folder: Path, what: str) -> Path:
    dataset_mesh = scene_mesh_in(folder)  # a public dataset's scene folder: the mesh its layout renders
    if dataset_mesh is not None:
        return dataset_mesh
    meshes = _meshes_in(folder)
    if not meshes:
        raise SpaceError(f"{what} holds no mesh ({', '.join(MESH_SUFFIXES)})")
    scannet = [m for m in meshes if m.name.endswith(SCANNET_MESH_SUFFIX)]
    if len(meshes) > 1 and len(scannet) == 1:  # a ScanNet scene folder: its other PLYs are derived copies
        return scannet[0]
    if len(meshes) > 1:
        listed = ", ".join(str(m.relative_to(folder)) for m in meshes[:20])
        more = f" and {len(meshes) - 20} more" if len(meshes) > 20 else ""
        raise SpaceError(f"{what} holds {len(meshes)} meshes, expected exactly one: {listed}{more}")
    return meshes[0]


# ---------------------------------------------------------------------------------------------
# up axis and the source -> world transform


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """3x3 rotation taking the unit vector `up` to +Z by the smallest angle (180 degrees: about +X)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c > 1 - 1e-15:
        return np.eye(3)
    if c < -1 + 1e-15:
        return np.diag([1.0, -1.0, -1.0])
    axis = np.cross(u, z)
    s = np.linalg.norm(axis)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + s * K + (1 - c) * (K @ K)
    # exact for axis-aligned inputs: kill rounding noise so 90-degree turns are integer matrices
    R[np.abs(R) < 1e-15] = 0.0
    return R


def source_to_world_matrix(up_source: np.ndarray, unit_scale: float) -> np.ndarray:
    """4x4 source -> world: scale by `unit_scale` (metres per unit), rotate `up_source` to +Z, no translation."""
    T = np.eye(4)
    T[:3, :3] = unit_scale * rotation_to_z(up_source)
    return T


# ---------------------------------------------------------------------------------------------
# semantics from PLY face properties

# Replica: class_id + object_id; Matterport3D region/house PLYs: category_id + segment_id
_CLASS_FIELDS = ("class_id", "category_id")
_INSTANCE_FIELDS = ("instance_id", "object_id", "segment_id")


def _field(data: Any, name: str) -> np.ndarray | None:
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


def _polygon_lengths(face_data: Any, n_faces: int) -> list[np.ndarray] | np.ndarray | None:
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


def _ply_triangle_polygons(mesh: trimesh.Trimesh, notes: list[str]) -> tuple[Any, np.ndarray, np.ndarray] | None:
    """(raw PLY face data, padded polygon vertex indices, raw polygon of each triangle), verified on positions."""
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
    vdata: Any = raw["vertex"].get("data") if "vertex" in raw else None
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


def _read_ply_semantics(
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


def _majority(labels: np.ndarray) -> np.ndarray:
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
        raise SpaceError(f"{source.name}: ScanNet labels found but the faces could not be matched: {'; '.join(notes)}")
    _, polys, tri_to_poly = table
    poly_class = _majority(vertex_class[polys])
    poly_instance = _majority(vertex_instance[polys])
    return poly_class[tri_to_poly].astype(np.int32), poly_instance[tri_to_poly].astype(np.int32), names, notes


def _classes_from_info_semantic(source: Path, face_instance: np.ndarray, notes: list[str]) -> np.ndarray | None:
    for cand in (source.parent / "info_semantic.json", source.parent / "habitat" / "info_semantic.json"):
        if not cand.is_file():
            continue
        try:
            id_to_label = np.asarray(json.loads(cand.read_text())["id_to_label"], dtype=np.int64)
        except (OSError, ValueError, KeyError, TypeError) as e:
            notes.append(f"{cand.name} unreadable ({e}); no class labels")
            return None
        inst = face_instance.astype(np.int64)
        valid = (inst >= 0) & (inst < len(id_to_label))
        out = np.zeros(len(inst), dtype=np.int32)
        out[valid] = np.maximum(id_to_label[inst[valid]], 0)
        return out
    return None


# ---------------------------------------------------------------------------------------------
# loading


_OBJ_NONFINITE = re.compile(rb"^v[ \t][^\n]*?(nan|inf)", re.IGNORECASE | re.MULTILINE)


def _nonfinite_vertices(source: Path, mesh: trimesh.Trimesh) -> int:
    """Vertices with NaN/inf coordinates, counted in the source: trimesh's processing merges a NaN
    vertex into another one instead of keeping it, so the loaded mesh alone does not show it."""
    bad = int((~np.isfinite(mesh.vertices).all(axis=1)).sum())
    raw = mesh.metadata.get("_ply_raw") if isinstance(mesh.metadata, dict) else None
    if raw and "vertex" in raw:
        try:
            xyz = np.column_stack([np.asarray(raw["vertex"]["data"][c], dtype=np.float64) for c in "xyz"])
            bad = max(bad, int((~np.isfinite(xyz).all(axis=1)).sum()))
        except (KeyError, TypeError, ValueError):
            pass
    elif source.suffix.lower() == ".obj":
        bad = max(bad, len(_OBJ_NONFINITE.findall(source.read_bytes())))
    return bad


def _has_texture(mesh: trimesh.Trimesh) -> bool:
    vis = mesh.visual
    if not isinstance(vis, trimesh.visual.TextureVisuals):
        return False
    uv = getattr(vis, "uv", None)
    if uv is None or len(uv) == 0:
        return False
    mat = getattr(vis, "material", None)
    img = getattr(mat, "image", None)
    if img is None:
        img = getattr(mat, "baseColorTexture", None)
    return img is not None


def load_space(
    path: str | Path,
    *,
    up_axis: str = "auto",
    unit_scale: float | str = "auto",
    up: Sequence[float] | None = None,
    source_to_world: Sequence[Sequence[float]] | None = None,
    extract_dir: str | Path | None = None,
    cloud_cache_dir: str | Path | None = None,
) -> LoadedSpace:
    """Load a space (mesh file, point cloud, folder or zip), validate it and bring it into the world frame.

    The mesh comes from `trimesh.load(source, force="mesh")` exactly (a point cloud: its cached
    reconstruction); `source_to_world` maps those coordinates to world metres (+Z up). The frame is
    `source_to_world` when given, else `up` (a source vector) or `up_axis` (a name, or "auto": detected),
    and `unit_scale` (metres per unit, or "auto": from the storey height). A zip is extracted into
    `extract_dir` (kept) or into a temporary folder removed after loading (then `source_path` is the zip).
    """
    if up_axis not in UP_AXES:
        raise SpaceError(f"up_axis {up_axis!r} is not one of {', '.join(UP_AXES)}")
    if unit_scale != "auto" and (isinstance(unit_scale, str) or not np.isfinite(unit_scale) or unit_scale <= 0):
        raise SpaceError(f"unit_scale must be 'auto' or a positive number of metres per unit, got {unit_scale!r}")
    if up is not None and (len(up) != 3 or not np.isfinite(up).all() or np.linalg.norm(up) < 1e-9):
        raise SpaceError(f"up must be a finite, non-zero vector [x, y, z], got {list(up)}")
    if source_to_world is not None:
        try:
            similarity_scale(source_to_world)
        except ValueError as e:
            raise SpaceError(str(e)) from None
    p = Path(path)
    tmp: Path | None = None
    if p.is_file() and p.suffix.lower() == ".zip" and extract_dir is None:
        tmp = Path(tempfile.mkdtemp(prefix="omnidata-space-"))
        extract_dir = tmp
    frame = FrameRequest(up_axis, unit_scale, None if up is None else np.asarray(up, dtype=np.float64),
                          None if source_to_world is None else np.asarray(source_to_world, dtype=np.float64))
    try:
        source = resolve_source(p, extract_dir)
        return _load(source, p if tmp is not None else source, frame,
                     None if cloud_cache_dir is None else Path(cloud_cache_dir))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


@dataclass(frozen=True)
class FrameRequest:
    """How the caller asked for the frame: source_to_world, else up or up_axis (or auto), and unit_scale."""

    up_axis: str
    unit_scale: float | str
    up: np.ndarray | None
    source_to_world: np.ndarray | None


def _read_mesh(
    source: Path, checksum: str, cloud_cache_dir: Path | None
) -> tuple[trimesh.Trimesh, dict[str, Any] | None]:
    """The triangle mesh of a source (sha256 `checksum`), and the reconstruction record when it was a point cloud."""
    name = source.name
    suffix = source.suffix.lower()
    try:
        if suffix in CLOUD_SUFFIXES:
            return mesh_cloud_cached(lambda: read_text_cloud(source), checksum, name, cloud_cache_dir)
        try:
            mesh = trimesh.load(source, force="mesh")
        except Exception as e:  # trimesh raises many kinds on corrupt input
            raise SpaceError(f"{name}: could not read the mesh ({type(e).__name__}: {e})") from None
        if suffix == ".ply" and isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) == 0:
            try:
                points = trimesh.load(source)  # a PLY of points: force="mesh" drops them
            except Exception:  # noqa: BLE001 - then it is not a readable cloud either: report the empty mesh
                points = None
            if len(getattr(points, "vertices", ())) > 0:
                return mesh_cloud_cached(lambda: cloud_from_ply(points), checksum, name, cloud_cache_dir)
    except CloudError as e:
        raise SpaceError(str(e)) from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise SpaceError(f"{name}: holds no triangle mesh (got {type(mesh).__name__})")
    return mesh, None


def resolve_frame(mesh: trimesh.Trimesh, suffix: str, frame: FrameRequest) -> tuple[np.ndarray, UpEstimate, UnitChoice]:
    """(source_to_world 4x4, how up was found, the units) of a mesh in its source frame."""
    if frame.source_to_world is not None:
        T = frame.source_to_world
        scale = similarity_scale(T)
        up = T[:3, :3].T @ [0.0, 0.0, 1.0] / scale
        return T, UpEstimate(up / np.linalg.norm(up), "source_to_world"), UnitChoice(
            scale, "source_to_world", "the scale of the given source_to_world")
    if frame.up is not None or frame.up_axis != "auto":
        given = frame.up if frame.up is not None else axis_vector(frame.up_axis)
        given = given / np.linalg.norm(given)
        est = floor_evidence(mesh, given) or UpEstimate(given, "given")
        est = UpEstimate(given, "given", est.floor_area, est.floor_fraction, storey_height=est.storey_height)
    else:
        est = estimate_up(mesh, suffix)
    if frame.unit_scale == "auto":
        try:
            units = choose_unit_scale(est.storey_height, float(mesh.extents.max()))
        except UnitError as e:
            raise SpaceError(str(e)) from None
    else:
        units = UnitChoice(float(frame.unit_scale), "given", "unit_scale given")
    return source_to_world_matrix(est.up, units.scale), est, units


def _dataset_scene(source: Path, frame: FrameRequest) -> tuple[DatasetScene | None, FrameRequest]:
    """The public dataset scene of a mesh (refusing an unusable release), and the frame: the dataset's
    convention (up axis, units, a shipped alignment) wherever the caller left the frame to detection."""
    try:
        scene = scene_of(source)
    except DatasetError as e:
        raise SpaceError(str(e)) from None
    if scene is None:
        return None, frame
    auto_up = frame.up_axis == "auto" and frame.up is None and frame.source_to_world is None
    if auto_up and frame.unit_scale == "auto" and scene.source_to_world is not None:
        return scene, FrameRequest("auto", "auto", None, scene.source_to_world)
    up_axis = scene.up_axis if auto_up and scene.up_axis is not None else frame.up_axis
    unit_scale = scene.unit_scale if frame.unit_scale == "auto" and scene.unit_scale is not None else frame.unit_scale
    return scene, FrameRequest(up_axis, unit_scale, frame.up, frame.source_to_world)


def _load(source: Path, recorded: Path, frame: FrameRequest, cloud_cache_dir: Path | None) -> LoadedSpace:
    name = source.name
    scene, frame = _dataset_scene(source, frame)
    from services.core.mesh_checks import check_source  # it imports SpaceError from here

    source_notes = check_source(source)  # truncation, counts over the limits, unsafe paths: before parsing
    checksum = sha256_file(source)
    mesh, reconstruction = _read_mesh(source, checksum, cloud_cache_dir)
    if len(mesh.vertices) == 0:
        raise SpaceError(f"{name}: the mesh is empty (no vertices)")
    if len(mesh.faces) == 0:
        raise SpaceError(f"{name}: the mesh has no faces; a triangle mesh or a point cloud is needed")
    bad = _nonfinite_vertices(source, mesh) if reconstruction is None else 0
    if bad:
        raise SpaceError(f"{name}: {bad} vertices have NaN or infinite coordinates")
    if mesh.faces.max() >= len(mesh.vertices) or mesh.faces.min() < 0:
        raise SpaceError(f"{name}: faces refer to vertices that do not exist")
    if float(mesh.area) <= 0:
        raise SpaceError(f"{name}: every face is degenerate (zero total area)")

    face_class, face_instance, notes = _read_ply_semantics(mesh, source) if reconstruction is None else (None, None, [])
    notes = source_notes + notes
    class_names = None
    if scene is not None and face_class is None and face_instance is None:
        try:
            labels = scene.labels(mesh)
        except DatasetError as e:
            raise SpaceError(f"{scene.dataset} scene {scene.scene_id}: {e}") from None
        if labels is not None:
            face_class, face_instance, class_names = labels.face_class, labels.face_instance, labels.class_names
            notes.extend(labels.notes)
    if face_class is None and face_instance is None and reconstruction is None:
        scannet = scannet_labels(mesh, source) if source.suffix.lower() == ".ply" else None
        if scannet is not None:
            face_class, face_instance, class_names, more = scannet
            notes.extend(more)
    T, est, units = resolve_frame(mesh, source.suffix.lower(), frame)
    scale = units.scale
    extent_m = float(mesh.extents.max()) * scale
    if extent_m > MAX_EXTENT_M:
        raise SpaceError(
            f"{name}: the mesh is {extent_m:.4g} m across with unit_scale {scale} m/unit "
            f"(more than {MAX_EXTENT_M / 1000:.0f} km): check unit_scale"
        )
    if extent_m < MIN_EXTENT_M:
        raise SpaceError(
            f"{name}: the mesh is {extent_m:.3g} m across with unit_scale {scale} m/unit "
            f"(less than {MIN_EXTENT_M * 1000:.0f} mm): check unit_scale"
        )
    if est.low_confidence:
        notes.append(f"up found with low confidence ({est.doubt()}): check it with `omnidata plan`, or set up/up_axis")
    has_texture = _has_texture(mesh)
    has_vertex_colors = getattr(mesh.visual, "kind", None) == "vertex"
    mesh.apply_transform(T)
    for n in notes:
        log.warning("%s: %s", name, n)
    return LoadedSpace(
        mesh=mesh,
        source_path=recorded,
        source_to_world=T,
        has_texture=has_texture,
        has_vertex_colors=has_vertex_colors,
        face_class=face_class,
        face_instance=face_instance,
        has_semantics=face_class is not None and face_instance is not None,
        bounds=np.array(mesh.bounds, dtype=np.float64),
        checksum=checksum,
        face_count=int(len(mesh.faces)),
        up_source=np.asarray(est.up, dtype=np.float64),
        up_method=est.method,
        warnings=tuple(notes),
        up_estimate=est,
        units=units,
        reconstruction=reconstruction,
        class_names=class_names,
    )
