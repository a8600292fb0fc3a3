"""Views of a posed capture (cameras.mode capture), in the world frame (metres, +Z up, OpenCV camera axes).

exact: one view per capture frame, at exactly the frame's camera (centre and rotation); the view is the square
pinhole about the optical axis with the frame's inscribed field of view (or cameras.capture_fov_deg), so its
rgb is the photo undistorted and resampled, and every other cue is rendered at that camera. The view's point
of interest is the surface the optical axis meets (it projects to the image centre, as for fixated views); a
frame whose axis meets no surface is reported and left out. Each view is scored for photo/geometry alignment
(services.scheduler.planning.alignment); views.min_alignment drops those below it.

fixated: the capture positions are the cameras of the usual point/view sampling; a view at a capture centre
fixating a point sees the scene through the same centre, so its rgb is the frame's photo turned by a rotation
homography. Views whose pixels the photo covers less than views.min_photo_coverage are dropped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, cast

import numpy as np

from services.core.domain.camera import intrinsics
from services.core.domain.capture_records import CapturePlanRecord, RefinedCamera
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import PlanError, SpacePlan
from services.core.ingest.capture.detect import BESIDE_DEPTH
from services.core.ingest.capture.model import Capture, CaptureFrame
from services.core.ingest.capture.resample import coverage_fraction
from services.scheduler.planning.alignment import alignment_score, score_summary, scoring_photo
from services.scheduler.planning.points import SampledPoints, visibility_matrix
from services.scheduler.planning.views import ViewArrays, fraction_summary, obliqueness, valid_fractions
from services.scheduler.planning.visibility import MeshQueries

if TYPE_CHECKING:  # loading imports the capture readers this module plans with
    from services.core.ingest.loading import LoadedSpace

FORMATS_LOOKED_FOR = (
    "transforms.json, a COLMAP model, a ScanNet export, 7-Scenes/BundleFusion frames, camera_poses.json"
)


def require_capture(space: LoadedSpace, space_name: str) -> Capture:
    """The space's capture in the world frame; PlanError saying what is missing otherwise."""
    capture = getattr(space, "capture", None)
    if capture is None:
        raise PlanError(
            f"space {space_name!r}: cameras.mode capture (or views.rgb_source photos) needs a posed capture "
            f"next to the scan (looked for {FORMATS_LOOKED_FOR}, in the folder or zip given, or at most "
            f"{BESIDE_DEPTH} folders down beside a single mesh file: give the folder for a deeper one); "
            "none was found"
        )
    if not capture.frames:
        why = "; ".join(capture.problems[:5]) or "no frames"
        raise PlanError(f"space {space_name!r}: the {capture.format} capture has no usable frame ({why})")
    return capture


def planning_capture(space: LoadedSpace, spec: JobSpec, space_name: str, q: MeshQueries
                     ) -> tuple[Capture, RefinedCamera | None]:
    """The capture the plan uses, its colour camera refined when cameras.capture_refine asks (with the
    record)."""
    capture = require_capture(space, space_name)
    if not (spec.cameras.capture_refine and capture.has_photos):
        return capture, None
    from services.scheduler.planning.refine import refine_colour_camera

    correction, record = refine_colour_camera(q, capture)
    return correction.capture(capture), record


def capture_positions(capture: Capture) -> np.ndarray:
    """(n, 3) camera centres, world metres."""
    return np.stack([f.center for f in capture.frames])


def roll_about_axis(world_to_camera: np.ndarray) -> float:
    """Roll (radians) of a camera about its optical axis relative to gravity, as
    services.core.domain.camera.look_at defines it (0: image up as close to +Z as possible; positive turns the
    image clockwise)."""
    R = world_to_camera[:3, :3]
    z = R[2]
    x0 = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x0) < 1e-9:
        x0 = np.cross(z, [0.0, 1.0, 0.0])
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z, x0)
    return float(np.arctan2(R[0] @ y0, R[0] @ x0))


def view_fov(spec: JobSpec, frame: CaptureFrame) -> float:
    """Field of view (radians) of an exact capture view of `frame`."""
    chosen = spec.cameras.capture_fov_deg
    if chosen is not None:
        return float(np.radians(chosen))
    if frame.K is None:
        return float(np.radians(spec.views.fov_mean_deg))
    return frame.inscribed_fov()


def exact_views(
    q: MeshQueries, capture: Capture, spec: JobSpec
) -> tuple[SampledPoints, ViewArrays, list[str]]:
    """Points (the surface on each frame's optical axis) and one view per frame that sees one (see module
    docs)."""
    c2w = np.stack([f.camera_to_world for f in capture.frames])
    centres, axes = c2w[:, :3, 3], c2w[:, :3, 2]
    dist, face = q.first_hit(centres, axes)
    good = np.flatnonzero(np.isfinite(dist) & (dist <= spec.params.max_depth_m))
    notes = [f"frame {capture.frames[i].name}: its optical axis meets no surface; no view"
             for i in np.flatnonzero(~np.isin(np.arange(len(c2w)), good))]
    positions = centres[good] + axes[good] * dist[good, None]
    normals = np.asarray(q.mesh.face_normals)[face[good]]
    flip = np.einsum("ij,ij->i", normals, centres[good] - positions) < 0
    normals[flip] *= -1.0
    seen = visibility_matrix(q, centres, positions, spec.points.los_tolerance_m)
    visible = tuple(
        np.union1d(np.flatnonzero(row), [c]).astype(np.int64) for row, c in zip(seen, good, strict=True)
    )
    n = len(good)
    W = np.stack([capture.frames[i].world_to_camera for i in good]) if n else np.zeros((0, 4, 4))
    views = ViewArrays(
        point_idx=np.arange(n), v=np.zeros(n, dtype=np.int64), camera_idx=good.astype(np.int64),
        world_to_camera=W,
        fov=np.array([view_fov(spec, capture.frames[i]) for i in good]),
        roll=np.array([roll_about_axis(w) for w in W]),
        obliqueness=obliqueness(normals, positions, centres[good]) if n else np.zeros(0),
        in_sight=np.ones(n, dtype=bool),
    )
    points = SampledPoints(
        positions, normals, visible, samples_drawn=len(c2w), requested=len(c2w), shortfall=None
    )
    return points, views, notes


def alignment_scores(q: MeshQueries, capture: Capture, views: ViewArrays) -> list[float | None]:
    """The alignment score of each view (None without photos or without enough geometric edges)."""
    if not capture.has_photos:
        return [None] * len(views)
    scores: list[float | None] = []
    for i in range(len(views)):
        frame = capture.frames[int(views.camera_idx[i])]
        photo = scoring_photo(str(capture.image_path(frame)), frame, float(views.fov[i]))
        scores.append(alignment_score(q, photo, frame, views.world_to_camera[i], float(views.fov[i])))
    return scores


def photo_coverages(capture: Capture, views: ViewArrays) -> np.ndarray:
    """(n,) predicted share of each view's pixels its frame's photo covers (1 for poses without photos)."""
    if not capture.has_photos:
        return np.ones(len(views))
    return np.array(
        [
            coverage_fraction(
                capture.frames[int(views.camera_idx[i])], intrinsics(float(views.fov[i]), 64),
                views.world_to_camera[i],
            )
            for i in range(len(views))
        ]
    )


def exact_capture_plan(space: LoadedSpace, spec: JobSpec, space_name: str, q: MeshQueries,
                       assemble: Callable[..., SpacePlan]) -> SpacePlan:
    """The plan of cameras.mode capture with capture_views exact (see the module docstring)."""
    capture, refined = planning_capture(space, spec, space_name, q)
    points, views, notes = exact_views(q, capture, spec)
    vs = spec.views
    scores = alignment_scores(q, capture, views)
    coverage = photo_coverages(capture, views)
    fractions = valid_fractions(q, views, spec.params.max_depth_m)
    keep = fractions >= vs.min_valid_fraction
    if vs.min_alignment > 0:
        keep &= np.array([s is not None and s >= vs.min_alignment for s in scores], dtype=bool)
    keep &= coverage >= vs.min_photo_coverage
    dropped = {
        "valid_fraction": int((fractions < vs.min_valid_fraction).sum()),
        "alignment": int(sum(s is None or s < vs.min_alignment for s in scores))
        if vs.min_alignment > 0
        else 0,
        "photo_coverage": int((coverage < vs.min_photo_coverage).sum()),
    }
    if not keep.all():
        notes.append("views dropped: " + ", ".join(f"{k} {v}" for k, v in dropped.items() if v))
    kept = np.flatnonzero(keep)
    views = views.subset(keep)
    points = SampledPoints(points.positions, points.normals, points.visible, points.samples_drawn,
                           points.requested, None)
    shortfall = (
        "; ".join(notes[:5]) + (f" (and {len(notes) - 5} more)" if len(notes) > 5 else "") if notes else None
    )
    plan = assemble(space_name, views.point_idx, capture_positions(capture), points, views, shortfall)
    by_camera = {int(views.camera_idx[j]): (scores[i], float(coverage[i])) for j, i in enumerate(kept)}
    planned = tuple(
        dataclasses.replace(
            v, alignment=by_camera[v.camera_idx][0], photo_coverage=by_camera[v.camera_idx][1]
        )
        for v in plan.views
    )
    record = capture_record(capture, scores, vs.min_alignment, [float(c) for c in coverage], len(planned))
    record["dropped"] = dropped
    # the manifest's per view
    record["view_alignment"] = {f"{v.point_idx}/{v.v}": v.alignment for v in planned}
    if refined is not None:
        record["refined"] = refined
    return dataclasses.replace(
        plan, views=planned, valid_fraction=fraction_summary(fractions, vs.min_valid_fraction), capture=record
    )


def fixated_coverage_keep(
    capture: Capture, views: ViewArrays, min_coverage: float
) -> tuple[np.ndarray, np.ndarray]:
    """(keep, coverage) of fixated views at capture positions: the photo must cover at least min_coverage."""
    coverage = photo_coverages(capture, views)
    return coverage >= min_coverage, coverage


def annotate_fixated(plan: SpacePlan, capture: Capture, min_coverage: float, dropped: int,
                     refined: RefinedCamera | None = None) -> SpacePlan:
    """A fixated capture plan with each view's photo coverage and the capture record."""
    planned = []
    for v in plan.views:
        frame = capture.frames[v.camera_idx]
        cov = coverage_fraction(frame, v.K, v.world_to_camera) if capture.has_photos else 1.0
        planned.append(dataclasses.replace(v, photo_coverage=cov))
    record = capture_record(capture, [], 0.0, [v.photo_coverage or 0.0 for v in planned], len(planned))
    record["dropped"] = {"photo_coverage": dropped}
    record["min_photo_coverage"] = min_coverage
    if refined is not None:
        record["refined"] = refined
    return dataclasses.replace(plan, views=tuple(planned), capture=record)


def capture_record(capture: Capture, scores: list[float | None], threshold: float, coverage: list[float],
                   n_views: int) -> CapturePlanRecord:
    """What job.json and the dashboard show of a capture plan."""
    cov = np.asarray(coverage, dtype=np.float64)
    # the summary's keys and the plan's (extra_checks: no ** into a TypedDict)
    return cast(CapturePlanRecord, {
        **capture.summary(),
        "views": n_views,
        "alignment": score_summary(scores, threshold),
        "photo_coverage": {"mean": float(cov.mean()), "min": float(cov.min())} if len(cov) else None,
    })


TEXTURE_PROBE_PX = 8  # probe rays per side when predicting a photo-textured view's coverage
TEXTURE_NEAREST = 16  # photos tried per view (the nearest capture cameras)


def textured_coverage(
    q: MeshQueries, capture: Capture, world_to_camera: np.ndarray, fov: np.ndarray
) -> np.ndarray:
    """(n,) predicted share of each view's surface pixels that some photo saw (views.rgb_source photos for
    cameras away from the capture): an 8 x 8 probe's surface points projected into the nearest photos,
    depth-tested from each photo's camera as the worker's texturing does
    (services.worker.inputs.phototexture)."""
    from services.core.ingest.capture.distortion import project_to_photo

    n = len(world_to_camera)
    out = np.zeros(n)
    centres = capture_positions(capture)
    g = (np.arange(TEXTURE_PROBE_PX) + 0.5) / (TEXTURE_PROBE_PX / 2) - 1.0
    gx, gy = np.meshgrid(g, g)
    for i in range(n):
        W = world_to_camera[i]
        t = np.tan(fov[i] / 2)
        d_cam = np.stack([gx.ravel() * t, gy.ravel() * t, np.ones(gx.size)], axis=1)
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        centre = -W[:3, :3].T @ W[:3, 3]
        dirs = d_cam @ W[:3, :3]
        dist, _ = q.first_hit(np.broadcast_to(centre, dirs.shape).copy(), dirs)
        hit = np.isfinite(dist)
        if not hit.any():
            continue
        pts = centre + dirs[hit] * dist[hit, None]
        seen = np.zeros(len(pts), dtype=bool)
        for j in np.argsort(np.linalg.norm(centres - centre, axis=1))[:TEXTURE_NEAREST]:
            f = capture.frames[int(j)]
            if f.K is None or f.width is None or f.height is None:
                continue
            cam = pts @ f.world_to_camera[:3, :3].T + f.world_to_camera[:3, 3]
            uv, front = project_to_photo(f.K, f.distortion, f.distortion_params, cam)
            inside = (
                front & (uv[:, 0] >= 0) & (uv[:, 0] <= f.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= f.height)
            )
            idx = np.flatnonzero(inside & ~seen)
            if not len(idx):
                continue
            to_pts = pts[idx] - centres[j]
            d = np.linalg.norm(to_pts, axis=1)
            first, _ = q.first_hit(np.broadcast_to(centres[j], to_pts.shape).copy(), to_pts / d[:, None])
            seen[idx[first >= d - (0.02 + 0.01 * d)]] = True
        out[i] = seen.mean()
    return out
