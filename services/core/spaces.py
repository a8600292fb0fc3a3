"""Loading a space (a scanned mesh) into the world frame shared by planning and rendering.

The planner and the worker both call `load_space`, so the pixels the worker renders line up with the
poses the planner chose. Frames and units:

- *source frame*: the coordinates `trimesh.load(source, force="mesh")` gives for the file, in the
  file's units. Its face order is the reference for the `fragments` cue (DESIGN.md section 5).
- *world frame*: metres, +Z up. `source_to_world` (4x4) = uniform scale `unit_scale` (metres per
  source unit) followed by the rotation that takes the detected up direction to +Z. There is **no
  translation** (a rotation-and-scale only: heights are measured from detected floors by the planner,
  not from z = 0), so the source origin stays the world origin.

Up-axis detection (`up_axis="auto"`), area-weighted normal clustering on axis-aligned families:

1. *Family*: for each source axis a, the area of faces whose normal lies within 15 degrees of +-a;
   the axis with the largest area is the vertical family (floors and ceilings of rooms, which are
   wider than tall, outweigh each pair of walls).
2. *Floor* (spaces scanned from inside, normals facing the free space): along the family axis, the
   area of faces in the lower half of the extent facing +a (a floor seen from above) and in the
   upper half facing -a (the same for the reversed axis). If the larger one covers >= 30 % of the
   bounding-box cross-section, the space has a floor and up points away from it: the end with more
   inward-facing horizontal area is the floor. Ties (a closed empty box: floor = ceiling) are broken
   by the total area facing each way (furniture tops face up and their bottoms are not scanned),
   then by the file convention.
   The direction is then refined to the area-weighted mean normal of those floor faces, so a slightly
   tilted scan is levelled (a floor built exactly on an axis stays exactly on it).
3. *Support base* (single objects, normals facing outwards): outward-facing area in the end 10 % that
   covers >= 15 % of the cross-section and >= 3 times the opposite end (the flat base of the bunny):
   up points away from the base, exactly along the axis.
4. Otherwise (a single object with no floor or base) the file convention: +Y up for .obj/.gltf/.glb,
   +Z up for .ply.

Semantic labels come from PLY face properties `class_id` and `instance_id` (Replica's `object_id` is
accepted as the instance). They are read from the raw PLY elements trimesh keeps in
`mesh.metadata['_ply_raw']` and mapped onto the triangles the way trimesh triangulates polygons
(triangles, then first and second halves of quads, then fans), and that mapping is verified on the
vertex positions. A Replica-style `info_semantic.json` (`id_to_label`) beside the mesh supplies
classes when only object ids are present.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
import stat
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import trimesh

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf")
UP_AXES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")
# file convention when no floor or base is found (DESIGN: glTF is +Y up; OBJ exporters mostly too)
CONVENTION_UP = {".obj": "+y", ".gltf": "+y", ".glb": "+y", ".ply": "+z"}

MAX_EXTENT_M = 10_000.0  # a 10 km scan means the units are wrong
MIN_EXTENT_M = 0.001  # everything inside 1 mm: same
ZIP_MAX_TOTAL_BYTES = 8 * 1024**3  # uncompressed size of all members
ZIP_MAX_RATIO = 200.0  # uncompressed / compressed, per member and in total
ZIP_MAX_MEMBERS = 20_000

_CONE_COS = float(np.cos(np.radians(15.0)))
_END_BAND = 0.10
_FLOOR_MIN_FRACTION = 0.30
_BASE_MIN_FRACTION = 0.15
_BASE_DOMINANCE = 3.0
_TIE_REL = 0.02


class SpaceError(ValueError):
    """A space that cannot be used, with a message meant for the user who uploaded it."""


@dataclass(frozen=True, eq=False)
class LoadedSpace:
    """A space in the world frame (metres, +Z up) plus what the planner and worker need to know."""

    mesh: trimesh.Trimesh  # world frame; faces in the order of trimesh.load(source, force="mesh")
    source_path: Path  # the mesh file that was loaded (a zip's path when extracted to a temporary folder)
    source_to_world: np.ndarray  # 4x4: source coordinates -> world metres (+Z up), no translation
    has_texture: bool  # UV coordinates and a texture image
    has_vertex_colors: bool
    face_class: np.ndarray | None  # int32 class id per face
    face_instance: np.ndarray | None  # int32 instance id per face
    has_semantics: bool  # both class and instance ids per face
    bounds: np.ndarray  # (2, 3) world-frame AABB, metres
    checksum: str  # sha256 hex of the mesh file
    face_count: int
    up_source: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # up, source frame
    up_method: str = "given"  # given | floor | base | convention | convention-tie
    warnings: tuple[str, ...] = ()


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
    meshes = _meshes_in(folder)
    if not meshes:
        raise SpaceError(f"{what} holds no mesh ({', '.join(MESH_SUFFIXES)})")
    if len(meshes) > 1:
        listed = ", ".join(str(m.relative_to(folder)) for m in meshes[:20])
        more = f" and {len(meshes) - 20} more" if len(meshes) > 20 else ""
        raise SpaceError(f"{what} holds {len(meshes)} meshes, expected exactly one: {listed}{more}")
    return meshes[0]


# ---------------------------------------------------------------------------------------------
# up axis and the source -> world transform


def _axis_vector(code: str) -> np.ndarray:
    v = np.zeros(3)
    v["xyz".index(code[1])] = 1.0 if code[0] == "+" else -1.0
    return v


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


def detect_up(mesh: trimesh.Trimesh, suffix: str) -> tuple[np.ndarray, str]:
    """Up direction in the source frame and how it was found (see the module docstring)."""
    normals = mesh.face_normals
    areas = mesh.area_faces
    centers = mesh.triangles_center
    ext = mesh.extents
    fam = [float(areas[np.abs(normals[:, a]) > _CONE_COS].sum()) for a in range(3)]
    a = int(np.argmax(fam))
    conv = _axis_vector(CONVENTION_UP.get(suffix, "+z"))
    if fam[a] <= 0:
        return conv, "convention"
    others = [i for i in range(3) if i != a]
    cross = max(float(ext[others[0]] * ext[others[1]]), 1e-300)
    lo, hi = mesh.bounds[:, a]
    band = _END_BAND * (hi - lo)
    mid = 0.5 * (lo + hi)
    n_a = normals[:, a]
    low = centers[:, a] <= lo + band
    high = centers[:, a] >= hi - band
    # halves rather than thin end bands: a tilted floor spans a good part of the height
    floor_pos = (centers[:, a] < mid) & (n_a > _CONE_COS)  # floor in the low half, up = +a
    floor_neg = (centers[:, a] > mid) & (n_a < -_CONE_COS)  # floor in the high half, up = -a
    fp, fn = float(areas[floor_pos].sum()), float(areas[floor_neg].sum())
    e = np.zeros(3)
    e[a] = 1.0
    if max(fp, fn) >= _FLOOR_MIN_FRACTION * cross:
        sign = 0.0
        if abs(fp - fn) > _TIE_REL * max(fp, fn):
            sign = 1.0 if fp > fn else -1.0
        else:
            up_area = float(areas[n_a > _CONE_COS].sum())
            down_area = float(areas[n_a < -_CONE_COS].sum())
            if abs(up_area - down_area) > _TIE_REL * max(up_area, down_area):
                sign = 1.0 if up_area > down_area else -1.0
        if sign == 0.0:
            # symmetric (a closed, empty box): the file convention decides when it names this axis
            sign = float(conv[a]) if conv[a] != 0 else 1.0
            return sign * e, "convention-tie"
        sel = floor_pos if sign > 0 else floor_neg
        mean = (normals[sel] * areas[sel, None]).sum(axis=0)
        up = mean / np.linalg.norm(mean)
        if np.arccos(np.clip(up @ (sign * e), -1.0, 1.0)) < 1e-9:
            up = sign * e
        return up, "floor"
    base_pos = float(areas[low & (n_a < -_CONE_COS)].sum())  # flat base at the low end facing down
    base_neg = float(areas[high & (n_a > _CONE_COS)].sum())
    if base_pos >= _BASE_MIN_FRACTION * cross and base_pos >= _BASE_DOMINANCE * base_neg:
        return e.copy(), "base"
    if base_neg >= _BASE_MIN_FRACTION * cross and base_neg >= _BASE_DOMINANCE * base_pos:
        return -e, "base"
    return conv, "convention"


def source_to_world_matrix(up_source: np.ndarray, unit_scale: float) -> np.ndarray:
    """4x4 source -> world: scale by `unit_scale` (metres per unit), rotate `up_source` to +Z, no translation."""
    T = np.eye(4)
    T[:3, :3] = unit_scale * rotation_to_z(up_source)
    return T


# ---------------------------------------------------------------------------------------------
# semantics from PLY face properties

_CLASS_FIELDS = ("class_id",)
_INSTANCE_FIELDS = ("instance_id", "object_id")


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


def _read_ply_semantics(
    mesh: trimesh.Trimesh, source: Path
) -> tuple[np.ndarray | None, np.ndarray | None, list[str]]:
    raw = mesh.metadata.get("_ply_raw") if isinstance(mesh.metadata, dict) else None
    notes: list[str] = []
    if not raw or "face" not in raw:
        return None, None, notes
    face = raw["face"]
    data = face.get("data")
    cls = next((c for c in (_field(data, f) for f in _CLASS_FIELDS) if c is not None), None)
    inst = next((c for c in (_field(data, f) for f in _INSTANCE_FIELDS) if c is not None), None)
    if cls is None and inst is None:
        return None, None, notes
    n_raw = len(cls if cls is not None else inst)  # type: ignore[arg-type]
    polys = _polygon_lengths(data, n_raw)
    if polys is None:
        notes.append("PLY face labels ignored: faces have no vertex_indices property")
        return None, None, notes
    tri_to_poly = _triangle_to_polygon(polys)
    if len(tri_to_poly) != len(mesh.faces):
        notes.append(
            f"PLY face labels ignored: {len(tri_to_poly)} triangles expected from {n_raw} polygons, "
            f"trimesh made {len(mesh.faces)}"
        )
        return None, None, notes
    # verify on positions: each triangle's first vertex must be a vertex of its polygon
    vdata = raw.get("vertex", {}).get("data")
    try:
        raw_xyz = np.column_stack([np.asarray(vdata[c], dtype=np.float64) for c in "xyz"])
        first = mesh.vertices[mesh.faces[:, 0]]
        if isinstance(polys, np.ndarray):
            padded = polys
        else:  # ragged polygons: pad with a repeat of their first vertex
            kmax = max(len(p) for p in polys)
            padded = np.array([np.pad(p, (0, kmax - len(p)), mode="edge") for p in polys])
        cand = raw_xyz[padded[tri_to_poly]]  # (F, k, 3)
        tol = 1e-6 * max(float(mesh.scale), 1e-9)  # trimesh merges vertices closer than ~1e-8
        ok = np.isclose(cand, first[:, None, :], rtol=0, atol=tol).all(axis=2).any(axis=1)
    except (KeyError, TypeError, ValueError, IndexError):
        ok = np.zeros(1, dtype=bool)
    if not ok.all():
        notes.append("PLY face labels ignored: could not align them with trimesh's triangles")
        return None, None, notes
    face_class = cls[tri_to_poly].astype(np.int32) if cls is not None else None
    face_instance = inst[tri_to_poly].astype(np.int32) if inst is not None else None
    if face_class is None and face_instance is not None:
        face_class = _classes_from_info_semantic(source, face_instance, notes)
    return face_class, face_instance, notes


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


def sha256_file(path: Path) -> str:
    """sha256 hex of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


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
    unit_scale: float = 1.0,
    extract_dir: str | Path | None = None,
) -> LoadedSpace:
    """Load a space (mesh file, folder or zip), validate it and bring it into the world frame.

    The mesh comes from `trimesh.load(source, force="mesh")` exactly; `source_to_world` maps those
    coordinates to world metres (+Z up). A zip is extracted into `extract_dir` (kept) or into a
    temporary folder removed after loading (then `source_path` is the zip itself).
    """
    if up_axis not in UP_AXES:
        raise SpaceError(f"up_axis {up_axis!r} is not one of {', '.join(UP_AXES)}")
    if not np.isfinite(unit_scale) or unit_scale <= 0:
        raise SpaceError(f"unit_scale must be a positive number of metres per unit, got {unit_scale}")
    p = Path(path)
    tmp: Path | None = None
    if p.is_file() and p.suffix.lower() == ".zip" and extract_dir is None:
        tmp = Path(tempfile.mkdtemp(prefix="omnidata-space-"))
        extract_dir = tmp
    try:
        source = resolve_source(p, extract_dir)
        return _load(source, p if tmp is not None else source, up_axis, unit_scale)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _load(source: Path, recorded: Path, up_axis: str, unit_scale: float) -> LoadedSpace:
    name = source.name
    from services.core.mesh_checks import check_source  # it imports SpaceError from here

    source_notes = check_source(source)  # truncation, counts over the limits, unsafe paths: before parsing
    try:
        mesh = trimesh.load(source, force="mesh")
    except Exception as e:  # trimesh raises many kinds on corrupt input
        raise SpaceError(f"{name}: could not read the mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise SpaceError(f"{name}: holds no triangle mesh (got {type(mesh).__name__})")
    if len(mesh.vertices) == 0:
        raise SpaceError(f"{name}: the mesh is empty (no vertices)")
    if len(mesh.faces) == 0:
        raise SpaceError(f"{name}: the mesh has no faces (a point cloud?); a triangle mesh is needed")
    bad = _nonfinite_vertices(source, mesh)
    if bad:
        raise SpaceError(f"{name}: {bad} vertices have NaN or infinite coordinates")
    if mesh.faces.max() >= len(mesh.vertices) or mesh.faces.min() < 0:
        raise SpaceError(f"{name}: faces refer to vertices that do not exist")
    extent_m = float(mesh.extents.max()) * unit_scale
    if extent_m > MAX_EXTENT_M:
        raise SpaceError(
            f"{name}: the mesh is {extent_m:.4g} m across with unit_scale {unit_scale} m/unit "
            f"(more than {MAX_EXTENT_M / 1000:.0f} km): check unit_scale"
        )
    if extent_m < MIN_EXTENT_M:
        raise SpaceError(
            f"{name}: the mesh is {extent_m:.3g} m across with unit_scale {unit_scale} m/unit "
            f"(less than {MIN_EXTENT_M * 1000:.0f} mm): check unit_scale"
        )
    if float(mesh.area) <= 0:
        raise SpaceError(f"{name}: every face is degenerate (zero total area)")

    face_class, face_instance, notes = _read_ply_semantics(mesh, source)
    notes = source_notes + notes
    if up_axis == "auto":
        up, method = detect_up(mesh, source.suffix.lower())
    else:
        up, method = _axis_vector(up_axis), "given"
    T = source_to_world_matrix(up, unit_scale)
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
        checksum=sha256_file(source),
        face_count=int(len(mesh.faces)),
        up_source=np.asarray(up, dtype=np.float64),
        up_method=method,
        warnings=tuple(notes),
    )
