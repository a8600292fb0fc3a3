"""Loading a space (a scanned mesh) into the world frame shared by planning and rendering.

The planner and the worker both call `load_space`, so the pixels the worker renders line up with the
poses the planner chose. Frames and units:

- *source frame*: the coordinates `trimesh.load(source, force="mesh")` gives for the file, in the
  file's units. Its face order is the reference for the `fragments` cue (face indices a
  user can look up in the file they gave us).
- *world frame*: metres, +Z up. `source_to_world` (4x4) = uniform scale `unit_scale` (metres per
  source unit) followed by the rotation that takes the up direction to +Z, with **no translation**
  (heights are measured from detected floors by the planner, not from z = 0), unless the user gives a
  whole `source_to_world` (rotation, uniform scale and translation), which is used as it is.

Up is given (`up_axis` name or `up` vector in source coordinates) or detected in any orientation
(`services.core.ingest.frame.gravity`: plane families of the face normals, then the floor, a support base or
the file convention); units are given or chosen from the storey height of rooms. How, and how sure, is kept in
`LoadedSpace.frame_record()` for job.json. Point clouds (.xyz, .pts, PLY without faces) are meshed first
(`services.core.ingest.pointcloud`); that mesh's faces are then the `fragments` reference.

Semantic labels are read by `services.core.ingest.labels`, the zip/folder is resolved by
`services.core.ingest.guard.archive` and the frame by `services.core.ingest.frame.resolve`.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from services.core.domain.frame_records import FrameRecord
from services.core.domain.frame_values import UP_AXES, similarity_scale
from services.core.domain.json_types import JSONObject
from services.core.ingest.capture.attach import capture_near  # a capture with the scan
from services.core.ingest.capture.model import Capture
from services.core.ingest.datasets import DatasetError, DatasetScene, scene_of
from services.core.ingest.errors import SpaceError
from services.core.ingest.frame.gravity import UpEstimate
from services.core.ingest.frame.reason_words import reason_words
from services.core.ingest.frame.recorded_gravity import read_recorded_up
from services.core.ingest.frame.resolve import FrameRequest, resolve_frame
from services.core.ingest.frame.unit_evidence import UnitChoice
from services.core.ingest.guard.archive import resolve_source
from services.core.ingest.guard.archive_rules import file_expansion_refusal
from services.core.ingest.guard.confine import ConfinedResolver, is_inside
from services.core.ingest.guard.mesh_checks import check_source
from services.core.ingest.guard.texture_limits import loaded_texture_refusal
from services.core.ingest.labels import read_ply_semantics, scannet_labels
from services.core.ingest.pointcloud import (
    CLOUD_SUFFIXES,
    CloudError,
    cloud_from_ply,
    mesh_cloud_cached,
    read_text_cloud,
)
from services.core.storage.base import sha256_file
from services.core.temp_dirs import owned_prefix

log = logging.getLogger(__name__)


MAX_EXTENT_M = 10_000.0  # a 10 km scan means the units are wrong
MIN_EXTENT_M = 0.001  # everything inside 1 mm: same
# the cameras' up this far from the scan's: the levelling (or the capture) is suspect
CAPTURE_UP_WARN_DEG = 10.0


@dataclass(frozen=True, eq=False)
class LoadedSpace:
    """A space in the world frame (metres, +Z up) plus what the planner and worker need to know."""

    mesh: trimesh.Trimesh  # world frame; faces in the order of trimesh.load(source, force="mesh")
    source_path: Path  # the mesh file that was loaded (a zip's path when extracted to a temporary folder)
    # 4x4: source coordinates -> world metres (+Z up); translation only when given
    source_to_world: np.ndarray
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
    reconstruction: JSONObject | None = None  # point clouds: how they were meshed
    class_names: dict[int, str] | None = None  # class id -> name, when the file names its classes
    capture: Capture | None = None  # a posed capture found with the scan, world frame

    def frame_record(self) -> FrameRecord:
        """What was detected about the frame, for job.json and `omnidata plan` (JSON-ready)."""
        scale = (self.units.scale if self.units is not None
                 else float(np.cbrt(np.linalg.det(self.source_to_world[:3, :3]))))
        est = self.up_estimate or UpEstimate(self.up_source, self.up_method)
        out: FrameRecord = {"up": est.record(scale)}
        if self.units is not None:
            out["units"] = self.units.record()
        if self.reconstruction is not None:
            out["reconstruction"] = self.reconstruction
        if self.class_names:
            out["class_names"] = {str(k): v for k, v in sorted(self.class_names.items())}
        if self.capture is not None:
            out["capture"] = self.capture.summary()
        return out

    def frame_summary(self) -> str:
        """One line: up, method, confidence and units (printed by `omnidata plan`)."""
        rec = self.frame_record()
        up = rec["up"]
        direction = ", ".join(f"{x:.4g}" for x in up["source_direction"])
        line = f"up [{direction}] ({up['method']}, {up['confidence']} confidence"
        if (probability := up.get("probability")) is not None:
            line += f", {100 * probability:.0f}% sure"
        if up["floor_area_m2"]:
            line += f", floor {up['floor_area_m2']:.3g} m2"
        if up["runner_up_angle_deg"] is not None:
            line += f", runner-up {up['runner_up_angle_deg']:.0f} deg away"
        if "reason" in up:
            line += f"; chosen for {up['reason']}"  # records stored before reasons were written have none
        line += ")"
        if "units" in rec:
            line += (f"; units: {rec['units']['unit']} x{rec['units']['unit_scale']:g} "
                     f"({rec['units']['reason']})")
        return line


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
        text = source.read_bytes()
        lower = text.lower()  # the pattern's cheap precondition (a scan has neither word: ~30 ms saved)
        if b"nan" in lower or b"inf" in lower:
            bad = max(bad, len(_OBJ_NONFINITE.findall(text)))
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
    accept_up_guess: bool = False,
    capture_up: Sequence[float] | np.ndarray | None = None,
) -> LoadedSpace:
    """Load a space (mesh file, point cloud, folder or zip), validate it and bring it into the world frame.

    The mesh comes from `trimesh.load(source, force="mesh")` exactly (a point cloud: its cached
    reconstruction); `source_to_world` maps those coordinates to world metres (+Z up). The frame is
    `source_to_world` when given, else `up` (a source vector) or `up_axis` (a name, or "auto": detected),
    and `unit_scale` (metres per unit, or "auto": from the storey height). A zip is extracted into
    `extract_dir` (kept) or into a temporary folder removed after loading (then `source_path` is the zip).
    A detected up that does not clearly beat a candidate levelling the scan differently raises UpAmbiguous
    unless `accept_up_guess`; `capture_up` (the capture's mean camera up, source frame) is strong evidence.
    """
    if up_axis not in UP_AXES:
        raise SpaceError(f"up_axis {up_axis!r} is not one of {', '.join(UP_AXES)}")
    if unit_scale != "auto" and (isinstance(unit_scale, str) or not np.isfinite(unit_scale)
                                 or unit_scale <= 0):
        raise SpaceError(f"unit_scale must be 'auto' or a positive number of metres per unit, "
                         f"got {unit_scale!r}")
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
        tmp = Path(tempfile.mkdtemp(prefix=owned_prefix("space")))
        extract_dir = tmp
    try:
        source = resolve_source(p, extract_dir)
        if p.is_dir() and not is_inside(source, Path(os.path.realpath(p))):
            raise SpaceError(f"{source.name}: a symbolic link to a file outside the folder {p.name}; "
                             "refusing it")
        capture = capture_near(Path(extract_dir) if p.suffix.lower() == ".zip" and extract_dir else p)
        if capture_up is None and capture is not None:
            capture_up = capture.mean_up()  # the cameras' up, source frame: evidence for levelling
        frame = FrameRequest(up_axis, unit_scale, None if up is None else np.asarray(up, dtype=np.float64),
                             None if source_to_world is None
                             else np.asarray(source_to_world, dtype=np.float64),
                             accept_up_guess,
                             None if capture_up is None else np.asarray(capture_up, dtype=np.float64),
                             _recorded_up(source))
        loaded = _load(source, p if tmp is not None else source, frame,
                       None if cloud_cache_dir is None else Path(cloud_cache_dir))
        return attach_capture(loaded, capture)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _recorded_up(source: Path) -> np.ndarray | None:
    """Up from a gravity recorded beside the mesh (strongest levelling evidence), source frame."""
    recorded = read_recorded_up(source.parent)
    if recorded is not None:
        log.info("%s: up %s from the gravity in %s", source.name, recorded.up.round(4).tolist(),
                 recorded.source)
    return None if recorded is None else recorded.up


def _load_confined(source: Path, **kwargs: Any) -> Any:  # trimesh.load's keywords and its untyped result
    """`trimesh.load(source)` whose every named file comes from the mesh's own folder (SpaceError
    otherwise)."""
    resolver = ConfinedResolver(source)
    try:
        loaded = trimesh.load(source, resolver=resolver, **kwargs)
    except Exception as e:  # trimesh raises many kinds on corrupt input
        refused = resolver.refusal()  # a refused buffer surfaces as trimesh's error: name the refusal instead
        raise SpaceError(
            f"{source.name}: {refused or f'could not read the mesh ({type(e).__name__}: {e})'}") from None
    refused = resolver.refusal() or loaded_texture_refusal(loaded)
    if refused is not None:  # trimesh carried on without the file (an untextured mesh): refuse the scan
        raise SpaceError(f"{source.name}: {refused}")
    return loaded


def _read_mesh(
    source: Path, checksum: str, cloud_cache_dir: Path | None
) -> tuple[trimesh.Trimesh, JSONObject | None, Callable[[], np.ndarray] | None]:
    """The triangle mesh of a source (sha256 `checksum`), the reconstruction record when it was a point
    cloud, and then a reader of its points (levelling weighs their own planes when the mesh shows none)."""
    name = source.name
    suffix = source.suffix.lower()
    try:
        if suffix in CLOUD_SUFFIXES:
            mesh, record = mesh_cloud_cached(lambda: read_text_cloud(source), checksum, name, cloud_cache_dir)
            return mesh, record, lambda: read_text_cloud(source).points
        mesh = _single_mesh(_load_confined(source, force="scene"))
        if suffix == ".ply" and isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) == 0:
            try:
                points = _load_confined(source)  # a PLY of points: force="mesh" drops them
            except SpaceError:  # then it is not a readable cloud either: report the empty mesh
                points = None
            if len(getattr(points, "vertices", ())) > 0:
                mesh, record = mesh_cloud_cached(lambda: cloud_from_ply(points), checksum, name,
                                                 cloud_cache_dir)
                return mesh, record, lambda: np.asarray(points.vertices, dtype=np.float64)
    except CloudError as e:
        raise SpaceError(str(e)) from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise SpaceError(f"{name}: holds no triangle mesh (got {type(mesh).__name__})")
    return mesh, None, None


def _single_mesh(scene: trimesh.Scene) -> trimesh.Trimesh:
    """scene.to_mesh(), what trimesh.load(force="mesh") returns, without its two copies of a scene that is one
    mesh placed once, untransformed (a PLY or OBJ of one object): that mesh itself, as trimesh.load without
    `force` returns it for those formats, its cache cleared as the copies' was (vertex normals a file states
    are dropped and computed from the faces, as before). Each copy also converted a coloured mesh's colours:
    the 7-Scenes kitchen's PLY loads in 0.14 CPU-s instead of 0.35."""
    if len(scene.geometry) == 1 and len(scene.graph.nodes_geometry) == 1:
        transform, name = scene.graph[scene.graph.nodes_geometry[0]]
        mesh = scene.geometry[name]
        if isinstance(mesh, trimesh.Trimesh) and np.array_equal(np.asarray(transform), np.eye(4)):
            mesh._cache.clear()  # type: ignore[no-untyped-call]  # as to_mesh's copies: the file's normals go
            return mesh
    return scene.to_mesh()


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
        return scene, replace(frame, up_axis="auto", unit_scale="auto", up=None,
                              source_to_world=scene.source_to_world)
    up_axis = scene.up_axis if auto_up and scene.up_axis is not None else frame.up_axis
    unit_scale = (scene.unit_scale if frame.unit_scale == "auto" and scene.unit_scale is not None
                  else frame.unit_scale)
    return scene, replace(frame, up_axis=up_axis, unit_scale=unit_scale)


def _check_mesh(source: Path, mesh: trimesh.Trimesh, reconstruction: JSONObject | None) -> None:
    """Refuse an empty mesh, one without faces, non-finite vertices, dangling faces or zero area."""
    name = source.name
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


def _check_extent(name: str, extent_source: float, scale: float) -> None:
    """Refuse a size in metres no scan has: the units are wrong."""
    extent_m = extent_source * scale
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


def _load(source: Path, recorded: Path, frame: FrameRequest, cloud_cache_dir: Path | None) -> LoadedSpace:
    name = source.name
    scene, frame = _dataset_scene(source, frame)
    # the rule its packed zip meets when planned: before parsing
    if problem := file_expansion_refusal(source):
        raise SpaceError(f"{name}: {problem}")
    source_notes = check_source(source)  # truncation, counts over the limits, unsafe paths: before parsing
    checksum = sha256_file(source)
    mesh, reconstruction, points = _read_mesh(source, checksum, cloud_cache_dir)
    _check_mesh(source, mesh, reconstruction)

    face_class, face_instance, notes = (read_ply_semantics(mesh, source) if reconstruction is None
                                        else (None, None, []))
    notes = source_notes + notes
    class_names = None
    if scene is not None and face_class is None and face_instance is None:
        try:
            labels = scene.labels(mesh)
        except DatasetError as e:
            raise SpaceError(f"{scene.dataset} scene {scene.scene_id}: {e}") from None
        if labels is not None:
            face_class, face_instance, class_names = (labels.face_class, labels.face_instance,
                                                      labels.class_names)
            notes.extend(labels.notes)
    if face_class is None and face_instance is None and reconstruction is None:
        scannet = scannet_labels(mesh, source) if source.suffix.lower() == ".ply" else None
        if scannet is not None:
            face_class, face_instance, class_names, more = scannet
            notes.extend(more)
    T, est, units = resolve_frame(mesh, source.suffix.lower(), frame, name, points)
    _check_extent(name, float(mesh.extents.max()), units.scale)
    if est.decision is not None and est.decision.geometry_prefers is not None:
        other = ", ".join(f"{x:.3g}" for x in est.decision.geometry_prefers.up)
        notes.append(f"the file's frame and the geometry disagree: the geometry alone would level it with up "
                     f"{other}; the file's frame decided ({reason_words(est.decision)})")
    if est.low_confidence:
        notes.append(f"up found with low confidence ({est.doubt()}): check it with `omnidata plan`, "
                     "or set up/up_axis")
    has_texture = _has_texture(mesh)
    has_vertex_colors = getattr(mesh.visual, "kind", None) == "vertex"
    mesh.apply_transform(T)
    for n in notes:
        log.warning("%s: %s", name, n)
    return LoadedSpace(
        mesh=mesh,
        source_path=recorded,
        source_to_world=T,
        has_texture=has_texture, has_vertex_colors=has_vertex_colors,
        face_class=face_class, face_instance=face_instance,
        has_semantics=face_class is not None and face_instance is not None,
        bounds=np.array(mesh.bounds, dtype=np.float64),
        checksum=checksum, face_count=int(len(mesh.faces)),
        up_source=np.asarray(est.up, dtype=np.float64), up_method=est.method,
        warnings=tuple(notes),
        up_estimate=est,
        units=units,
        reconstruction=reconstruction,
        class_names=class_names,
    )


def attach_capture(loaded: LoadedSpace, capture: Capture | None) -> LoadedSpace:
    """`loaded` with `capture` (source frame) moved into its world frame, when there is one."""
    if capture is None:
        return loaded
    for problem in capture.problems[:20]:
        log.warning("%s capture: %s", capture.format, problem)
    if capture.problems:  # shown by `omnidata plan` and kept in job.json with the other warnings
        more = len(capture.problems) - 5
        shown = "; ".join(capture.problems[:5]) + (f"; and {more} more" if more > 0 else "")
        note = (f"{capture.format} capture: {len(capture.frames)} frames read, "
                f"{len(capture.problems)} problems: {shown}")
        loaded = replace(loaded, warnings=(*loaded.warnings, note))
    world = capture.in_world(loaded.source_to_world)
    up = world.mean_up()  # the cameras' evidence of up, checked against the scan's levelling
    if up is not None:
        angle = float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
        note = f"the cameras' up (right axes level) is {angle:.1f} deg from the scan's up"
        world = replace(world, notes=(*world.notes, note), up_angle_deg=angle)
        if angle > CAPTURE_UP_WARN_DEG:
            loaded = replace(loaded, warnings=(*loaded.warnings, f"{note}: check the levelling"))
    return replace(loaded, capture=world)
