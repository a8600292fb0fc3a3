"""What every plan of a space shares, planned whole or in chunks: its cameras and sampled points, the uuids,
and the plan's value objects built from the sampling's arrays. World frame: metres, +Z up."""

from __future__ import annotations

import hashlib
import uuid as uuidlib
from collections.abc import Sequence

import numpy as np

from services.core.domain.jobspec import CameraSpec, JobSpec
from services.core.domain.plan import CameraPose, PlanError, PlannedView, PointOfInterest
from services.core.ingest.loading import LoadedSpace
from services.scheduler.planning.cameras import generate_cameras, object_cameras, provided_cameras
from services.scheduler.planning.points import SampledPoints, sample_points
from services.scheduler.planning.views import ViewArrays
from services.scheduler.planning.visibility import MeshQueries

VALID_REPORT_VIEWS = 2000  # views probed for job.json's valid-fraction distribution when none are dropped


def plan_uuid(salt: bytes, kind: str, idx: int) -> str:
    h = hashlib.sha256(salt + f"/{kind}/{idx}".encode()).digest()
    return str(uuidlib.UUID(bytes=h[:16], version=4))


def join_notes(*parts: str | None) -> str | None:
    text = "; ".join(p for p in parts if p)
    return text or None


def check_enough_cameras(n_cameras: int, spec: JobSpec, space_name: str) -> None:
    """PlanError when fewer cameras exist than a point needs views: no point could be planned."""
    ps = spec.points
    if n_cameras < ps.min_views:
        raise PlanError(
            f"space {space_name!r} has {n_cameras} cameras (mode {spec.cameras.mode!r}) but "
            f"points.min_views is {ps.min_views}: no point could be seen by enough cameras; lower "
            "min_views or cameras.min_spacing_m, or raise cameras.max_count"
        )


def place_cameras(space: LoadedSpace, camera_spec: CameraSpec, q: MeshQueries, rng: np.random.Generator
                   ) -> tuple[np.ndarray, str, tuple[np.ndarray, float] | None]:
    """(camera positions, their source, an object's camera sphere (centre, radius) or None)."""
    if camera_spec.mode == "generate":
        return generate_cameras(q, camera_spec, rng), "generated", None
    if camera_spec.mode == "provided":
        return provided_cameras(camera_spec), "provided", None
    cams, centre, radius = object_cameras(space.mesh, camera_spec, rng)
    return cams, "object", (centre, radius)  # trajectory clips orbit the object's points


def sample_space_points(q: MeshQueries, cams: np.ndarray, spec: JobSpec, space_name: str,
                        rng: np.random.Generator) -> SampledPoints:
    """The points of interest seen from `cams` (points.count, or points.per_camera per camera)."""
    ps = spec.points
    check_enough_cameras(len(cams), spec, space_name)
    count = ps.count if ps.count is not None else max(1, int(round(ps.per_camera * len(cams))))
    return sample_points(q, cams, ps, count, rng)


def camera_poses(cams: np.ndarray, source: str, camera_spec: CameraSpec,
                 salt: bytes) -> tuple[CameraPose, ...]:
    """The plan's cameras: given poses keep their uuids, the others get one from the plan's salt."""
    poses = camera_spec.poses
    given = [p.uuid for p in poses] if source == "provided" and poses else [None] * len(cams)
    return tuple(CameraPose(idx=i, position=cams[i], source=source,
                            uuid=given[i] or plan_uuid(salt, "camera", i))
                 for i in range(len(cams)))


def points_of(sampled: SampledPoints, sampled_idx: Sequence[int] | np.ndarray, first: int,
              salt: bytes) -> tuple[PointOfInterest, ...]:
    """The sampled points `sampled_idx` as the plan's points first, first+1, ..."""
    return tuple(PointOfInterest(idx=k, position=sampled.positions[p], normal=sampled.normals[p],
                                 uuid=plan_uuid(salt, "point", k), camera_idxs=sampled.visible[p])
                 for k, p in enumerate(sampled_idx, start=first))


def planned_views(views: ViewArrays, resolution: int) -> tuple[PlannedView, ...]:
    return tuple(
        PlannedView(point_idx=int(views.point_idx[i]), v=int(views.v[i]), camera_idx=int(views.camera_idx[i]),
                    world_to_camera=views.world_to_camera[i], fov=float(views.fov[i]),
                    roll=float(views.roll[i]), resolution=int(resolution),
                    obliqueness=float(views.obliqueness[i]), in_sight=bool(views.in_sight[i]))
        for i in range(len(views)))
