"""Point clouds (PLY without faces, .xyz, .pts) meshed on ingest by screened Poisson reconstruction.

Units and frames: everything stays in the cloud's source frame and units; the mesh then goes through
the same up/unit detection as any scan. The reconstruction (pymeshlab's screened Poisson, one thread so
the same cloud always gives the same triangles, the reference of the `fragments` cue) is trimmed in two
ways so it does not invent surfaces where nothing was scanned: vertices whose Poisson sample density is
in the lowest `TRIM_DENSITY_QUANTILE`, and faces farther than `TRIM_SPACINGS` median point spacings
from every point. Colours go to the vertices from the nearest point. Normals, when the cloud has none,
are estimated from 10 neighbours and turned towards a viewpoint (`viewpoint`): the camera at the origin of
a cloud stored around its camera (turned or not), else the bounding box's centre (a room scanned from
inside; give normals for single objects). The mesh is cached per cloud checksum and parameters.
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from services.core.domain.json_types import JSONObject
from services.core.ingest.frame.camera_frame import origin_is_camera
from services.core.ingest.guard.confine import ConfinedResolver
from services.core.user_cache import MESHED, TEMP_PREFIX, touch, user_cache_dir

CLOUD_SUFFIXES = (".xyz", ".pts")
MIN_POINTS = 1000
POISSON_SAMPLES_PER_NODE = 1.5
POISSON_DEPTH_RANGE = (6, 10)
TRIM_DENSITY_QUANTILE = 0.02
TRIM_SPACINGS = 2.5
MAX_POINTS = 20_000_000
RECONSTRUCTION_VERSION = 5  # bump when the method changes: cached meshes are keyed by it


class CloudError(ValueError):
    """A point cloud that cannot be meshed, with a message for the user."""


@dataclass(frozen=True)
class Cloud:
    """Points in the source frame, with optional unit normals and 8-bit RGB colours."""

    points: np.ndarray  # (N, 3) float64
    normals: np.ndarray | None  # (N, 3) float64
    colors: np.ndarray | None  # (N, 3) uint8


def _unit_rows(a: np.ndarray) -> bool:
    n = np.linalg.norm(a, axis=1)
    return bool(len(n) and np.all(np.abs(n - 1.0) < 0.05))


def _colors(a: np.ndarray) -> np.ndarray:
    scale = 255.0 if a.max(initial=0.0) <= 1.0 else 1.0  # floats in [0, 1] or bytes
    return np.clip(np.rint(a * scale), 0, 255).astype(np.uint8)


def read_text_cloud(path: Path) -> Cloud:
    """An .xyz/.pts file: rows of x y z, then normals and/or colours (and an intensity in .pts)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            first = f.readline().split()
            skip = 1 if len(first) == 1 else 0  # .pts starts with the point count
            rows = np.loadtxt(path, skiprows=skip, ndmin=2, dtype=np.float64)
    except (OSError, ValueError) as e:
        raise CloudError(f"{path.name}: not a readable point list ({e})") from None
    cols = rows.shape[1] if rows.size else 0
    if cols < 3:
        raise CloudError(f"{path.name}: expected rows of at least x y z, got {cols} columns")
    pts, rest = rows[:, :3], rows[:, 3:]
    if rest.shape[1] in (4, 7):  # .pts: an intensity before the colours
        rest = rest[:, 1:]
    normals = colors = None
    if rest.shape[1] >= 6:
        a, b = rest[:, :3], rest[:, 3:6]
        normals, colors = (a, _colors(b)) if _unit_rows(a) else (b, _colors(a))
    elif rest.shape[1] == 3:
        if _unit_rows(rest):
            normals = rest
        else:
            colors = _colors(rest)
    return Cloud(pts, normals, colors)


def cloud_from_ply(mesh: trimesh.PointCloud | trimesh.Trimesh) -> Cloud:
    """The points of a faceless PLY as trimesh loaded them (a PointCloud, or an empty-faced Trimesh)."""
    pts = np.asarray(mesh.vertices, dtype=np.float64)
    colors = None
    raw = mesh.metadata.get("_ply_raw") if isinstance(getattr(mesh, "metadata", None), dict) else None
    vdata = raw.get("vertex", {}).get("data") if raw else None
    normals = None
    if vdata is not None and getattr(vdata, "dtype", None) is not None and vdata.dtype.names:
        names = vdata.dtype.names
        if all(n in names for n in ("nx", "ny", "nz")):
            normals = np.column_stack([np.asarray(vdata[n], dtype=np.float64) for n in ("nx", "ny", "nz")])
        if all(n in names for n in ("red", "green", "blue")):
            colors = _colors(
                np.column_stack([np.asarray(vdata[n], dtype=np.float64) for n in ("red", "green", "blue")])
            )
        if len(normals if normals is not None else pts) != len(pts):
            normals, colors = None, None
    if colors is None:
        vc = getattr(getattr(mesh, "visual", None), "vertex_colors", None)
        if vc is None:
            vc = getattr(mesh, "colors", None)
        if vc is not None and len(vc) == len(pts):
            colors = np.asarray(vc)[:, :3].astype(np.uint8)
    return Cloud(pts, normals, colors)


def _check(cloud: Cloud, name: str) -> None:
    n = len(cloud.points)
    if not np.isfinite(cloud.points).all():
        raise CloudError(f"{name}: {int((~np.isfinite(cloud.points).all(axis=1)).sum())} points have NaN or "
                         "infinite coordinates")
    if n < MIN_POINTS:
        raise CloudError(f"{name}: a point cloud of {n} points is too sparse to mesh (at least {MIN_POINTS})")
    if n > MAX_POINTS:
        raise CloudError(f"{name}: {n} points exceed the limit {MAX_POINTS}; subsample the cloud")
    ext = np.ptp(cloud.points, axis=0)
    if np.sort(ext)[1] <= 0:
        raise CloudError(
            f"{name}: the points lie on a line or at one spot (extents {ext.tolist()}): nothing to mesh"
        )


def poisson_depth(n_points: int) -> int:
    """Octree depth whose surface cells (about 4^depth) hold `POISSON_SAMPLES_PER_NODE` points each."""
    lo, hi = POISSON_DEPTH_RANGE
    return int(np.clip(np.ceil(np.log(max(n_points, 1) / POISSON_SAMPLES_PER_NODE) / np.log(4.0)), lo, hi))


def median_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest neighbour (source units), repeated points counted once: a
    laser station's points repeat (54% of the PCL room scan's coincide with another, a fifth
    of them at the scanner's own mount), and a spacing of 0 would trim the whole surface away."""
    tree = cKDTree(points)
    d, _ = tree.query(points[:: max(1, len(points) // 20_000)], k=2)
    if (d[:, 1] == 0).any():
        distinct = np.unique(points, axis=0)
        return median_spacing(distinct) if len(distinct) < len(points) else 0.0
    return float(np.median(d[:, 1]))


def viewpoint(points: np.ndarray) -> tuple[np.ndarray, str]:
    """Where estimated normals are turned towards, and its name: the camera at the origin of a cloud stored
    around its camera, turned or not (`origin_is_camera`: a depth frame, an RGB-D fusion in its first camera's
    frame, a phone session started there), else the bounding box's centre (a room scanned from inside).
    Towards the centre, a table top above the centre's height would face down, as the underside of something
    hanging from a ceiling."""
    if origin_is_camera(points):
        return np.zeros(3), "the camera at the source origin (a cloud stored around its camera)"
    return 0.5 * (points.min(axis=0) + points.max(axis=0)), "the bounding-box centre"


def load_blenders_embree() -> None:
    """pymeshlab and Blender each ship Embree under one soname, libembree4.so.4 (4.3.3 and 4.4.0), and the
    first one loaded serves the whole process: after a meshing, `import bpy` failed (undefined symbol
    rtcGetSceneTraversable), so a worker that meshed a cloud could not render it. Where bpy is installed its
    Embree is loaded first, without importing bpy; pymeshlab runs on it, as it does once bpy is imported."""
    try:
        spec = importlib.util.find_spec("bpy")
    except (ImportError, ValueError):  # blocked (a test without bpy) or half-imported
        return
    lib = Path(spec.origin).parent / "lib" / "libembree4.so.4" if spec and spec.origin else None
    if lib is not None and lib.exists():
        ctypes.CDLL(str(lib))


def reconstruct(cloud: Cloud, name: str) -> tuple[trimesh.Trimesh, JSONObject]:
    """Mesh a cloud (see the module docstring); returns the mesh (source frame) and its job.json record."""
    load_blenders_embree()
    import pymeshlab

    _check(cloud, name)
    pts = cloud.points
    ms = pymeshlab.MeshSet()
    kwargs: dict[str, np.ndarray] = {"vertex_matrix": pts}
    if cloud.normals is not None:
        kwargs["v_normals_matrix"] = cloud.normals
    ms.add_mesh(pymeshlab.Mesh(**kwargs))
    estimated = cloud.normals is None
    if estimated:
        eye, seen_from = viewpoint(pts)
        ms.compute_normal_for_point_clouds(k=10, smoothiter=0, flipflag=True, viewpos=eye)
    depth = poisson_depth(len(pts))
    ms.generate_surface_reconstruction_screened_poisson(
        depth=depth, samplespernode=POISSON_SAMPLES_PER_NODE, preclean=True, threads=1)
    out = ms.current_mesh()
    verts = np.asarray(out.vertex_matrix(), dtype=np.float64)
    faces = np.asarray(out.face_matrix(), dtype=np.int64)
    density = np.asarray(out.vertex_scalar_array(), dtype=np.float64)
    if len(faces) == 0:
        raise CloudError(f"{name}: surface reconstruction gave no faces (too few or too scattered points)")
    keep_v = density >= np.quantile(density, TRIM_DENSITY_QUANTILE)
    spacing = median_spacing(pts)
    centers = verts[faces].mean(axis=1)
    dist, _ = cKDTree(pts).query(centers)
    keep = keep_v[faces].all(axis=1) & (dist <= TRIM_SPACINGS * spacing)
    mesh = trimesh.Trimesh(verts, faces[keep], process=False)
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise CloudError(
            f"{name}: nothing of the reconstructed surface lies near the points; the cloud is too sparse"
        )
    if cloud.colors is not None:
        _, nearest = cKDTree(pts).query(mesh.vertices)
        rgba = np.column_stack([cloud.colors[nearest], np.full(len(nearest), 255, np.uint8)])
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    record: JSONObject = {
        "method": "screened_poisson (pymeshlab), trimmed by density and distance to the points",
        "parameters": {
            "depth": depth, "samples_per_node": POISSON_SAMPLES_PER_NODE,
            "trim_density_quantile": TRIM_DENSITY_QUANTILE, "trim_spacings": TRIM_SPACINGS,
            "median_spacing": spacing,
            "normals": f"estimated (k=10, towards {seen_from})" if estimated else "given",
            "version": RECONSTRUCTION_VERSION,
        },
        "point_count": int(len(pts)),
        "face_count": int(len(mesh.faces)),
        "fragments": "face indices of this reconstruction (the cached mesh), which source_to_world also maps",
        "has_colors": cloud.colors is not None,
    }
    return mesh, record


def default_cache_dir() -> Path:
    """Where meshed clouds are kept: $OMNIDATA_DATA_DIR/meshed (default ~/.omnidata/meshed)."""
    return user_cache_dir(MESHED)


def mesh_cloud_cached(cloud_loader: Callable[[], Cloud], checksum: str, name: str,
                      cache_dir: Path | None = None) -> tuple[trimesh.Trimesh, JSONObject]:
    """The mesh of a cloud, reconstructed once per (checksum, method version) and then read from the cache.

    `cloud_loader()` returns the Cloud; it is only called on a cache miss.
    """
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    key = hashlib.sha256(f"{checksum}:{RECONSTRUCTION_VERSION}".encode()).hexdigest()[:32]
    ply, meta = cache / f"{key}.ply", cache / f"{key}.json"
    if ply.is_file() and meta.is_file():
        try:
            # our own file, but read like any scan: nothing it names is opened outside the cache folder
            mesh = trimesh.load(ply, force="mesh", process=False, resolver=ConfinedResolver(ply))
            record = json.loads(meta.read_text())
            if isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) == record.get("face_count"):
                touch(ply)  # used: kept longest when the folder is pruned
                return mesh, {**record, "cached": True}
        except (OSError, ValueError):
            pass
    built, record = reconstruct(cloud_loader(), name)
    data = built.export(file_type="ply")
    assert isinstance(data, bytes)  # trimesh writes binary PLY
    # the mesh as the cache will give it back, so the first load and later ones agree to the bit
    stream = trimesh.util.wrap_as_stream(data)  # type: ignore[no-untyped-call]  # trimesh is untyped
    mesh = trimesh.load(stream, file_type="ply", force="mesh", process=False)
    assert isinstance(mesh, trimesh.Trimesh)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        for path, blob in ((ply, data), (meta, json.dumps(record).encode())):
            fd, tmp = tempfile.mkstemp(dir=cache, prefix=TEMP_PREFIX[MESHED])
            with os.fdopen(fd, "wb") as f:
                f.write(blob)
            os.replace(tmp, path)  # atomic: concurrent loaders keep whichever lands last, both identical
    except OSError:
        pass  # a read-only cache only costs time
    return mesh, {**record, "cached": False}
