"""The source -> world transform of a space: up (given or detected) and units (given or chosen).

`source_to_world` (4x4) = uniform scale `unit_scale` (metres per source unit) followed by the rotation that
takes the up direction to +Z, with no translation (heights are measured from detected floors by the
planner, not from z = 0), unless the user gives a whole `source_to_world`, which is used as it is.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache, partial

import numpy as np
import trimesh

from services.core.domain.frame_values import similarity_scale
from services.core.domain.frame_words import ambiguity_line, units_ambiguity_line
from services.core.ingest.errors import SpaceError, UnitsAmbiguous, UpAmbiguous
from services.core.ingest.frame.camera_frame import in_camera_frame, origin_is_camera
from services.core.ingest.frame.candidates import FileFrame
from services.core.ingest.frame.gravity import (
    SurfaceSamples,
    UpEstimate,
    axis_vector,
    estimate_up,
    file_frame,
    floor_evidence,
    guess_candidates,
)
from services.core.ingest.frame.plane_families import plane_families
from services.core.ingest.frame.point_planes import point_samples
from services.core.ingest.frame.unit_evidence import UnitChoice, UnitError, choose_units

FRAME_KEYS = ("up", "units", "reconstruction", "class_names", "valid_fraction", "capture")


def frame_of(record: Mapping[str, object] | None) -> dict[str, object] | None:
    """The frame part of a space record (validation, plan summary): what the API shows; None when absent."""
    if not record:
        return None
    return {k: record[k] for k in FRAME_KEYS if k in record} or None


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
    """4x4 source -> world: scale by `unit_scale` (metres per unit), rotate `up_source` to +Z, no
    translation."""
    T = np.eye(4)
    T[:3, :3] = unit_scale * rotation_to_z(up_source)
    return T


@dataclass(frozen=True)
class FrameRequest:
    """How the caller asked for the frame: source_to_world, else up or up_axis (or auto), and unit_scale."""

    up_axis: str
    unit_scale: float | str
    up: np.ndarray | None
    source_to_world: np.ndarray | None
    accept_up_guess: bool = False
    capture_up: np.ndarray | None = None
    recorded_up: np.ndarray | None = None  # up from a recorded gravity (`recorded_gravity`), source frame


def resolve_frame(mesh: trimesh.Trimesh, suffix: str, frame: FrameRequest, name: str = "the scan",
                  points: Callable[[], np.ndarray] | None = None
                  ) -> tuple[np.ndarray, UpEstimate, UnitChoice]:
    """(source_to_world 4x4, how up was found, the units) of a mesh in its source frame; UpAmbiguous or
    UnitsAmbiguous (`name`). `points`: a point cloud's points (source frame): its camera's frame and single
    view are judged on them, and where its mesh shows no floor, their own planes are weighed
    (`point_planes`)."""
    if frame.source_to_world is not None:
        T = frame.source_to_world
        scale = similarity_scale(T)
        up = T[:3, :3].T @ [0.0, 0.0, 1.0] / scale
        return T, UpEstimate(up / np.linalg.norm(up), "source_to_world"), UnitChoice(
            scale, "source_to_world", "the scale of the given source_to_world")
    samples: SurfaceSamples | None = None
    file: FileFrame | None = None
    cloud: np.ndarray | None = None
    if frame.up is not None or frame.up_axis != "auto":
        given = frame.up if frame.up is not None else axis_vector(frame.up_axis)
        given = given / np.linalg.norm(given)
        est = floor_evidence(mesh, given) or UpEstimate(given, "given")
        est = UpEstimate(given, "given", est.floor_area, est.floor_fraction, storey_height=est.storey_height)
    else:
        # a cloud's points, as its normals were turned (services.core.ingest.pointcloud.viewpoint)
        cloud = None if points is None else points()
        camera = cloud is not None and in_camera_frame(cloud)
        file = file_frame(suffix, cloud=cloud is not None, camera=camera,
                          origin_camera=cloud is not None and origin_is_camera(cloud))
        # a cloud's own planes, read at most once (0.6 s for 60,000 points), where the mesh is not enough
        cloud_samples = None if cloud is None else cache(partial(point_samples, cloud))
        est = estimate_up(mesh, suffix, frame.capture_up, recorded_up=frame.recorded_up, file=file,
                          view_points=cloud,
                          frame_axes=None if cloud_samples is None else partial(_plane_axes, cloud_samples))
        if est.method in _NO_FLOOR and cloud_samples is not None:
            samples = cloud_samples()
            if samples is not None:
                from_points = estimate_up(mesh, suffix, frame.capture_up, recorded_up=frame.recorded_up,
                                          samples=samples, file=file, view_points=cloud)
                est = from_points if from_points.method == "floor" else est
    if frame.unit_scale == "auto":
        try:
            units = choose_units(mesh, est.up, est.storey_height)
        except UnitError as e:
            if samples is not None and not frame.accept_up_guess:  # a cloud: ask for its up first
                _refuse_unknown_up(mesh, suffix, name, samples, file, cloud)
            raise SpaceError(str(e)) from None
    else:
        units = UnitChoice(float(frame.unit_scale), "given", "unit_scale given")
    if est.ambiguous and not frame.accept_up_guess:
        rec = est.record(units.scale)
        if est.decision is not None and est.decision.gravity_conflict:
            said = f"{name}: the gravity recorded beside it and its geometry disagree, so"
            raise UpAmbiguous(ambiguity_line(said, rec["candidates"], None), rec["candidates"])
        raise UpAmbiguous(ambiguity_line(name, rec["candidates"], est.margin), rec["candidates"])
    if est.method in ("convention", "base") and not frame.accept_up_guess:
        _refuse_space_sized_guess(mesh, suffix, est.up, units.scale, name, samples, file, cloud)
    if units.ambiguous and not frame.accept_up_guess:
        raise UnitsAmbiguous(units_ambiguity_line(name, list(units.candidates)), list(units.candidates))
    return source_to_world_matrix(est.up, units.scale), est, units


def _plane_axes(cloud_samples: Callable[[], SurfaceSamples | None]) -> list[np.ndarray]:
    """A cloud's plane directions read from its own points (`point_planes`)."""
    samples = cloud_samples()
    return [] if samples is None else [f for f, _ in plane_families(samples.normals, samples.areas)]


_NO_FLOOR = ("convention", "base")  # methods that found no floor in the mesh
AGREE_DEG = 3.0
SPACE_EXTENT_M = 3.0  # an object this large is a space: a room needs its up found, not an object's rule


def _refuse_space_sized_guess(mesh: trimesh.Trimesh, suffix: str, up: np.ndarray, unit_scale: float,
                              name: str, samples: SurfaceSamples | None = None, file: FileFrame | None = None,
                              cloud: np.ndarray | None = None) -> None:
    """UpAmbiguous when no floor was found in a scan the size of a space, unless every candidate's evidence
    agrees with the object rule's `up` (the format's up, or a support base). `samples`: a cloud's own planes,
    weighed before its mesh's; `file` and `cloud`: what the file says and a cloud's points, weighed as where a
    floor is found."""
    extent_m = float(mesh.extents.max()) * unit_scale
    if extent_m < SPACE_EXTENT_M or _faces_outward(mesh):
        return
    decision = (None if samples is None else guess_candidates(mesh, suffix, samples, file, cloud)
                ) or guess_candidates(mesh, suffix, None, file, cloud)
    if decision is None or decision.runner_up is None:
        raise SpaceError(f"{name}: no floor and no dominant planes found in a space {extent_m:.3g} m across, "
                         "so its up cannot be told; give it with --up=X,Y,Z or --up-axis (API: spec field "
                         "up or up_axis)")
    if not decision.ambiguous and float(decision.best.up @ up) >= np.cos(np.radians(AGREE_DEG)):
        return
    candidates = [c.record(unit_scale) for c in decision.shown]
    raise UpAmbiguous(ambiguity_line(f"{name}: no floor found in a space {extent_m:.3g} m across, so",
                                     candidates, None), candidates)


def _refuse_unknown_up(mesh: trimesh.Trimesh, suffix: str, name: str, samples: SurfaceSamples,
                       file: FileFrame | None, cloud: np.ndarray | None) -> None:
    """UpAmbiguous naming a cloud's candidates (source units) when neither a floor nor its units were found:
    without the up, no storey tells the units, and the candidates its planes rank are the question to ask."""
    decision = guess_candidates(mesh, suffix, samples, file, cloud)
    if decision is None or decision.runner_up is None:
        return
    candidates = [c.record() for c in decision.shown]
    raise UpAmbiguous(ambiguity_line(f"{name}: no floor found and its units unknown, so", candidates, None),
                      candidates)


def _faces_outward(mesh: trimesh.Trimesh) -> bool:
    """True for a shape seen from outside (an object, whatever its size): its faces, weighted by area, face
    away from its centre; a space scanned from inside faces in (-0.3 to -0.6 on the real rooms of
    bench/scans)."""
    centers, normals, areas = mesh.triangles_center, mesh.face_normals, mesh.area_faces
    offsets = centers - np.average(centers, axis=0, weights=areas)
    lengths = np.linalg.norm(offsets, axis=1)
    keep = lengths > 0
    outwardness = np.einsum("ij,ij->i", offsets[keep], normals[keep]) / lengths[keep]
    return float(np.average(outwardness, weights=areas[keep])) > 0.2
