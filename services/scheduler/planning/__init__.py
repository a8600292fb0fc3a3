"""Planning: cameras, points of interest and views of one space, as a pure function of its inputs.

`make_plan(space, spec, rng, space_name)` runs cameras -> points -> views with the given
`numpy.random.Generator` only (no global RNG, bpy, SQL, S3 or Celery), so the same seed and inputs
give a byte-identical `plan_to_json`. World frame: metres, +Z up (see services.core.ingest.loading).
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
import uuid as uuidlib

import numpy as np

from services.core.domain.jobspec import CameraSpec, JobSpec
from services.core.domain.keys import check_name
from services.core.domain.plan import (
    CameraPose,
    PlanError,
    PlannedView,
    PointOfInterest,
    SpacePlan,
    clip_shortfall,
)
from services.core.ingest.loading import LoadedSpace
from services.scheduler.planning.cameras import generate_cameras, object_cameras, provided_cameras
from services.scheduler.planning.points import SampledPoints, sample_points
from services.scheduler.planning.trajectory import ClipNote, longest_run, trajectory
from services.scheduler.planning.views import (
    ViewArrays,
    fraction_summary,
    nonfixated_keep,
    valid_fractions,
    wide_baseline,
)
from services.scheduler.planning.visibility import MeshQueries

__all__ = ["make_plan", "space_rng", "PlanError"]

VALID_REPORT_VIEWS = 2000  # views probed for job.json's valid-fraction distribution when none are dropped


def space_rng(seed: int, space_name: str) -> np.random.Generator:
    """The Generator for one space of a job: depends on the job seed and the space name only, so
    adding a space to a job does not change the plans of the others."""
    digest = hashlib.sha256(space_name.encode()).digest()
    return np.random.default_rng([int(seed), int.from_bytes(digest[:8], "little")])


def _uuid(salt: bytes, kind: str, idx: int) -> str:
    h = hashlib.sha256(salt + f"/{kind}/{idx}".encode()).digest()
    return str(uuidlib.UUID(bytes=h[:16], version=4))


def make_plan(
    space: LoadedSpace,
    spec: JobSpec,
    rng: np.random.Generator,
    space_name: str,
    *,
    timings: dict[str, float] | None = None,
) -> SpacePlan:
    """Sample cameras, points and views of `space` as `spec` says; `timings` (if given) receives
    seconds per stage and the number of rays cast."""
    check_name("space", space_name)
    t0 = time.perf_counter()
    stamp: dict[str, float] = {}
    q = MeshQueries(space.mesh)
    salt = rng.bytes(16)
    cs = spec.cameras
    orbit = None  # an object's camera sphere: trajectory clips orbit its points
    capture, refined = None, None
    if cs.mode == "capture":
        from services.scheduler.planning import capture_views

        if cs.capture_views == "exact":
            return capture_views.exact_capture_plan(
                space, spec, space_name, q, lambda name, pidx, cams, pts, views, short: _assemble(
                    name, salt, cams, "capture", cs, pts, np.unique(pidx), views, spec.views.resolution, short, []))
        capture, refined = capture_views.planning_capture(space, spec, space_name, q)
        cams, source = capture_views.capture_positions(capture), "capture"
    elif cs.mode == "generate":
        cams, source = generate_cameras(q, cs, rng), "generated"
    elif cs.mode == "provided":
        cams, source = provided_cameras(cs), "provided"
    else:
        cams, centre, radius = object_cameras(space.mesh, cs, rng)
        source, orbit = "object", (centre, radius)
    t1 = time.perf_counter()
    stamp["cameras"] = t1 - t0
    ps = spec.points
    if len(cams) < ps.min_views:
        raise PlanError(
            f"space {space_name!r} has {len(cams)} cameras (mode {cs.mode!r}) but points.min_views is "
            f"{ps.min_views}: no point could be seen by enough cameras; lower min_views or "
            "cameras.min_spacing_m, or raise cameras.max_count"
        )
    count = ps.count if ps.count is not None else max(1, int(round(ps.per_camera * len(cams))))
    sampled = sample_points(q, cams, ps, count, rng)
    t2 = time.perf_counter()
    stamp["points"] = t2 - t1

    vs = spec.views
    notes: list[ClipNote] = []
    if vs.mode == "wide_baseline":
        views = wide_baseline(sampled.positions, sampled.normals, sampled.visible, cams, vs, ps.max_views, rng)
    else:
        views, notes = trajectory(
            sampled.positions, sampled.normals, sampled.visible, cams, vs, ps.max_views, q,
            ps.los_tolerance_m, cs.clearance_m, rng, orbit,
        )
    shortfall = sampled.shortfall
    photo_dropped = 0
    if capture is not None and len(views):  # fixated views at capture positions: enough of the photo in view
        covered, _ = capture_views.fixated_coverage_keep(capture, views, vs.min_photo_coverage)
        photo_dropped = int((~covered).sum())
        views = views.subset(covered)
        n_covered = np.bincount(views.point_idx, minlength=len(sampled.positions))
        views = views.subset(n_covered[views.point_idx] >= ps.min_views)
    elif spec.uses_photos() and len(views):  # photo-textured views: enough surface some photo saw
        from services.scheduler.planning import capture_views as photo_views

        textured = photo_views.textured_coverage(q, photo_views.require_capture(space, space_name), views.world_to_camera,
                                                 views.fov)
        ok = textured >= vs.min_photo_coverage
        if vs.mode == "trajectory":  # as for min_valid_fraction: no gaps inside a clip
            ok = _longest_runs(views.point_idx, ok, vs.trajectory_min_frames)
        photo_dropped = int((~ok).sum())
        views = views.subset(ok)
        if vs.mode != "trajectory":
            n_covered = np.bincount(views.point_idx, minlength=len(sampled.positions))
            views = views.subset(n_covered[views.point_idx] >= ps.min_views)
        if photo_dropped:
            shortfall = _join(shortfall, f"views.min_photo_coverage {vs.min_photo_coverage} dropped {photo_dropped} "
                                         "photo-textured views")
    keep_points = np.unique(views.point_idx) if notes or photo_dropped else np.arange(len(sampled.positions))
    if vs.nonfixated_pruning and len(views):
        crossing = nonfixated_keep(views, sampled.positions, sampled.visible, vs.resolution)
        if vs.mode == "trajectory":  # as for min_valid_fraction below: no gaps inside a clip
            crossing = _longest_runs(views.point_idx, crossing, vs.trajectory_min_frames)
        views = views.subset(crossing)
        n_views = np.bincount(views.point_idx, minlength=len(sampled.positions))
        keep_points = np.flatnonzero(n_views >= ps.min_views)
        views = views.subset(np.isin(views.point_idx, keep_points))
        if len(keep_points) < len(sampled.positions):
            note = (
                f"nonfixated pruning kept {len(keep_points)} of {len(sampled.positions)} points "
                f"(>= {ps.min_views} views that each see another point)"
            )
            shortfall = _join(shortfall, note)
    if vs.min_valid_fraction > 0:
        fractions = valid_fractions(q, views, spec.params.max_depth_m)
        valid_summary = fraction_summary(fractions, vs.min_valid_fraction)
    else:  # only reported: an even sample of the views bounds the cost on big plans
        sample = np.unique(np.linspace(0, len(views) - 1, min(len(views), VALID_REPORT_VIEWS)).astype(np.int64))
        valid_summary = fraction_summary(valid_fractions(q, views.subset(sample), spec.params.max_depth_m), 0.0)
        valid_summary["sampled_of"] = len(views)
    if vs.min_valid_fraction > 0 and len(views):
        passing = fractions >= vs.min_valid_fraction
        if vs.mode == "trajectory":  # a frame dropped from inside a clip would make its video jump
            passing = _longest_runs(views.point_idx, passing, vs.trajectory_min_frames)
        views = views.subset(passing)
        n_views = np.bincount(views.point_idx, minlength=len(sampled.positions))
        kept = keep_points[n_views[keep_points] >= ps.min_views]
        views = views.subset(np.isin(views.point_idx, kept))
        dropped = int((~passing).sum())
        if dropped or len(kept) < len(keep_points):
            cut = " (each clip keeps its longest run of frames above it)" if vs.mode == "trajectory" else ""
            note = (
                f"views.min_valid_fraction {vs.min_valid_fraction} dropped {dropped} views{cut}; "
                f"{len(kept)} of {len(keep_points)} points keep >= {ps.min_views} views"
            )
            shortfall = _join(shortfall, note)
        keep_points = kept
    t3 = time.perf_counter()
    stamp["views"] = t3 - t2

    plan = _assemble(
        space_name, salt, cams, source, cs, sampled, keep_points, views, vs.resolution, shortfall, notes
    )
    plan = dataclasses.replace(plan, valid_fraction=valid_summary)
    if capture is not None:
        plan = capture_views.annotate_fixated(plan, capture, vs.min_photo_coverage, photo_dropped, refined)
    stamp["assemble"] = time.perf_counter() - t3
    if timings is not None:
        timings.update(stamp)
        timings["rays"] = float(q.rays)
        timings["total"] = time.perf_counter() - t0
    return plan


def _longest_runs(point_idx: np.ndarray, ok: np.ndarray, min_frames: int) -> np.ndarray:
    """Of views sorted by point (the frames of each point's clip in order), the longest run of `ok` frames per
    point, or none where that run is shorter than `min_frames`."""
    keep = np.zeros(len(ok), dtype=bool)
    bounds = np.flatnonzero(np.diff(point_idx)) + 1
    for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(ok)], strict=True):
        a, b = longest_run(ok[lo:hi], np.ones(hi - lo, dtype=bool))
        if b - a >= min_frames:
            keep[lo + a:lo + b] = True
    return keep


def _join(*parts: str | None) -> str | None:
    text = "; ".join(p for p in parts if p)
    return text or None


def _assemble(
    space_name: str,
    salt: bytes,
    cams: np.ndarray,
    source: str,
    cs: CameraSpec,
    sampled: SampledPoints,
    keep_points: np.ndarray,
    views: ViewArrays,
    resolution: int,
    shortfall: str | None,
    notes: list[ClipNote],
) -> SpacePlan:
    given = [p.uuid for p in cs.poses] if source == "provided" and cs.poses else [None] * len(cams)
    cameras = tuple(
        CameraPose(idx=i, position=cams[i], source=source, uuid=given[i] or _uuid(salt, "camera", i))
        for i in range(len(cams))
    )
    new_idx = np.full(len(sampled.positions), -1, dtype=np.int64)
    new_idx[keep_points] = np.arange(len(keep_points))
    points = tuple(
        PointOfInterest(
            idx=k, position=sampled.positions[p], normal=sampled.normals[p],
            uuid=_uuid(salt, "point", k), camera_idxs=sampled.visible[p],
        )
        for k, p in enumerate(keep_points)
    )
    # renumber v within each point after pruning
    pidx = new_idx[views.point_idx]
    order = np.lexsort((views.v, pidx))
    pidx = pidx[order]
    counts = np.bincount(pidx, minlength=len(points)) if len(pidx) else np.zeros(len(points), dtype=np.int64)
    v = np.arange(len(pidx)) - np.repeat(np.cumsum(counts) - counts, counts)
    planned = tuple(
        PlannedView(
            point_idx=int(pidx[i]), v=int(v[i]), camera_idx=int(views.camera_idx[o]),
            world_to_camera=views.world_to_camera[o], fov=float(views.fov[o]), roll=float(views.roll[o]),
            resolution=int(resolution), obliqueness=float(views.obliqueness[o]), in_sight=bool(views.in_sight[o]),
        )
        for i, o in enumerate(order)
    )
    # clip notes name the points by their index in the plan (None: dropped)
    clip_notes = tuple(n.as_dict(int(new_idx[n.point]) if new_idx[n.point] >= 0 else None) for n in notes)
    shortfall = _join(shortfall, clip_shortfall(clip_notes, len(sampled.positions)))
    return SpacePlan(
        space_name=space_name, cameras=cameras, points=points, views=planned, shortfall=shortfall,
        clip_notes=clip_notes,
    )
