"""Planning: cameras, points of interest and views of one space, as a pure function of its inputs.

`make_plan(space, spec, rng, space_name)` runs cameras -> points -> views with the given
`numpy.random.Generator` only (no global RNG, bpy, SQL, S3 or Celery), so the same seed and inputs
give a byte-identical `plan_to_json`. World frame: metres, +Z up (see services.core.ingest.loading).

`plan_chunks` gives the same plan in chunks of whole points. The specs that plan in chunks (`plans_in_chunks`)
have one planner, planning.stream, and `make_plan` collects its chunks; the others (capture cameras,
trajectories, filters that need every view) are planned whole here and cut into chunks.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time

import numpy as np

from services.core.domain.jobspec import CameraSpec, JobSpec, ViewSpec
from services.core.domain.keys import check_name
from services.core.domain.plan import PlanError, SpacePlan, ValidFractionSummary, clip_shortfall
from services.core.domain.plan_budget import plans_in_chunks
from services.core.ingest.capture.model import Capture
from services.core.ingest.loading import LoadedSpace
from services.scheduler.planning.parts import (
    VALID_REPORT_VIEWS,
    camera_poses,
    join_notes,
    place_cameras,
    planned_views,
    points_of,
    sample_space_points,
)
from services.scheduler.planning.paths import longest_run
from services.scheduler.planning.points import SampledPoints
from services.scheduler.planning.stream import PlanChunks, cut_plan, stream_plan
from services.scheduler.planning.trajectory import ClipNote, trajectory
from services.scheduler.planning.views import (
    ViewArrays,
    fraction_summary,
    nonfixated_keep,
    valid_fractions,
    wide_baseline,
)
from services.scheduler.planning.visibility import MeshQueries

__all__ = ["make_plan", "plan_chunks", "space_rng", "PlanError"]


def space_rng(seed: int, space_name: str) -> np.random.Generator:
    """The Generator for one space of a job: depends on the job seed and the space name only, so
    adding a space to a job does not change the plans of the others."""
    digest = hashlib.sha256(space_name.encode()).digest()
    return np.random.default_rng([int(seed), int.from_bytes(digest[:8], "little")])


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
    if plans_in_chunks(spec):
        return stream_plan(space, spec, rng, space_name, None, timings).collect()
    return _plan_whole(space, spec, rng, space_name, timings)


def plan_chunks(space: LoadedSpace, spec: JobSpec, rng: np.random.Generator, space_name: str,
                chunk_views: int) -> PlanChunks:
    """The plan of `space` in chunks of whole points of about `chunk_views` views (at least one point)."""
    check_name("space", space_name)
    if plans_in_chunks(spec):
        return stream_plan(space, spec, rng, space_name, chunk_views)
    return cut_plan(_plan_whole(space, spec, rng, space_name, None), chunk_views)


def _plan_whole(space: LoadedSpace, spec: JobSpec, rng: np.random.Generator, space_name: str,
                timings: dict[str, float] | None) -> SpacePlan:
    """make_plan of the specs that need every view at once before any is final."""
    t0 = time.perf_counter()
    stamp: dict[str, float] = {}
    q = MeshQueries(space.mesh)
    salt = rng.bytes(16)
    camera_spec = spec.cameras
    capture, refined = None, None
    if camera_spec.mode == "capture":
        from services.scheduler.planning import capture_views

        if camera_spec.capture_views == "exact":
            return _exact_capture_plan(space, spec, space_name, q, salt)
        capture, refined = capture_views.planning_capture(space, spec, space_name, q)
        cams, source, orbit = capture_views.capture_positions(capture), "capture", None
    else:
        cams, source, orbit = place_cameras(space, camera_spec, q, rng)
    stamp["cameras"] = (t1 := time.perf_counter()) - t0
    sampled = sample_space_points(q, cams, spec, space_name, rng)
    stamp["points"] = (t2 := time.perf_counter()) - t1

    vs = spec.views
    views, notes = _choose_views(sampled, cams, spec, q, rng, orbit)
    shortfall = sampled.shortfall
    photo_dropped = 0  # fixated views at capture positions: enough of the photo in view
    if capture is not None and len(views):
        views, photo_dropped = _keep_photo_covered(capture, views, len(sampled.positions), spec)
    elif spec.uses_photos() and len(views):  # photo-textured views: enough surface some photo saw
        views, photo_dropped, shortfall = _keep_photo_textured(
            space, space_name, q, views, len(sampled.positions), spec, shortfall
        )
    keep_points = _kept_points(views, len(sampled.positions), bool(notes or photo_dropped), vs)
    if vs.nonfixated_pruning and len(views):
        views, keep_points, shortfall = _prune_nonfixated(views, sampled, spec, shortfall)
    fractions, valid_summary = _valid_fractions(q, views, spec)
    if fractions is not None and len(views):
        views, keep_points, shortfall = _drop_low_valid(views, fractions, len(sampled.positions), keep_points,
                                                        spec, shortfall)
    stamp["views"] = (t3 := time.perf_counter()) - t2

    plan = _assemble(space_name, salt, cams, source, camera_spec, sampled, keep_points, views, vs.resolution,
                     shortfall, notes)
    plan = dataclasses.replace(plan, valid_fraction=valid_summary)
    if capture is not None:
        plan = capture_views.annotate_fixated(plan, capture, vs.min_photo_coverage, photo_dropped, refined)
    stamp["assemble"] = time.perf_counter() - t3
    if timings is not None:
        timings.update(stamp, rays=float(q.rays), total=time.perf_counter() - t0)
    return plan


def _exact_capture_plan(
    space: LoadedSpace, spec: JobSpec, space_name: str, q: MeshQueries, salt: bytes
) -> SpacePlan:
    """The plan of capture_views: exact (the captured photos' own poses are the views)."""
    from services.scheduler.planning import capture_views

    return capture_views.exact_capture_plan(
        space, spec, space_name, q, lambda name, pidx, cams, pts, views, short: _assemble(
            name, salt, cams, "capture", spec.cameras, pts, np.unique(pidx), views, spec.views.resolution,
            short, []))


def _keep_photo_covered(
    capture: Capture, views: ViewArrays, n_points: int, spec: JobSpec
) -> tuple[ViewArrays, int]:
    """Capture views that show enough of their photo, and points left with enough of them; (views,
    dropped)."""
    from services.scheduler.planning import capture_views

    covered, _ = capture_views.fixated_coverage_keep(capture, views, spec.views.min_photo_coverage)
    photo_dropped = int((~covered).sum())
    views = views.subset(covered)
    n_covered = np.bincount(views.point_idx, minlength=n_points)
    return views.subset(n_covered[views.point_idx] >= spec.points.min_views), photo_dropped


def _keep_photo_textured(
    space: LoadedSpace, space_name: str, q: MeshQueries, views: ViewArrays, n_points: int, spec: JobSpec,
    shortfall: str | None,
) -> tuple[ViewArrays, int, str | None]:
    """Photo-textured views that show enough surface some photo saw; (views, dropped, shortfall)."""
    from services.scheduler.planning import capture_views as photo_views

    vs, ps = spec.views, spec.points
    textured = photo_views.textured_coverage(
        q, photo_views.require_capture(space, space_name), views.world_to_camera, views.fov
    )
    ok = textured >= vs.min_photo_coverage
    if vs.mode == "trajectory":  # as for min_valid_fraction: no gaps inside a clip
        ok = _longest_runs(views.point_idx, ok, vs.trajectory_min_frames)
    photo_dropped = int((~ok).sum())
    views = views.subset(ok)
    if vs.mode != "trajectory":
        n_covered = np.bincount(views.point_idx, minlength=n_points)
        views = views.subset(n_covered[views.point_idx] >= ps.min_views)
    if photo_dropped:
        shortfall = join_notes(
            shortfall,
            f"views.min_photo_coverage {vs.min_photo_coverage} dropped {photo_dropped} photo-textured views",
        )
    return views, photo_dropped, shortfall


def _valid_fractions(
    q: MeshQueries, views: ViewArrays, spec: JobSpec
) -> tuple[np.ndarray | None, ValidFractionSummary]:
    """(each view's predicted valid fraction when views.min_valid_fraction filters, else None; the
    summary)."""
    vs = spec.views
    if vs.min_valid_fraction > 0:
        fractions = valid_fractions(q, views, spec.params.max_depth_m)
        return fractions, fraction_summary(fractions, vs.min_valid_fraction)
    # only reported: an even sample of the views bounds the cost on big plans
    sample = np.unique(np.linspace(0, len(views) - 1, min(len(views), VALID_REPORT_VIEWS)).astype(np.int64))
    summary = fraction_summary(valid_fractions(q, views.subset(sample), spec.params.max_depth_m), 0.0)
    summary["sampled_of"] = len(views)
    return None, summary


def _choose_views(
    sampled: SampledPoints, cams: np.ndarray, spec: JobSpec, q: MeshQueries, rng: np.random.Generator,
    orbit: tuple[np.ndarray, float] | None,
) -> tuple[ViewArrays, list[ClipNote]]:
    """The views of the sampled points: wide-baseline views, or trajectory clips (with notes on cut clips)."""
    vs, ps = spec.views, spec.points
    if vs.mode == "wide_baseline":
        return wide_baseline(sampled.positions, sampled.normals, sampled.visible, cams, vs, ps.max_views, rng,
                             ps.min_views), []
    return trajectory(
        sampled.positions, sampled.normals, sampled.visible, cams, vs, ps.max_views, q,
        ps.los_tolerance_m, spec.cameras.clearance_m, rng, orbit,
    )


def _kept_points(views: ViewArrays, n_points: int, dropped: bool, vs: ViewSpec) -> np.ndarray:
    """The points that kept views when some may have lost them all (cut clips, photo coverage, pitch
    thinning), else every point."""
    if dropped or vs.pitch_quantiles_deg is not None:
        return np.unique(views.point_idx)
    return np.arange(n_points)


def _prune_nonfixated(views: ViewArrays, sampled: SampledPoints, spec: JobSpec, shortfall: str | None
                      ) -> tuple[ViewArrays, np.ndarray, str | None]:
    """Keep the views that see another point, and the points left with enough of them."""
    vs, ps = spec.views, spec.points
    crossing = nonfixated_keep(views, sampled.positions, sampled.visible, vs.resolution)
    if vs.mode == "trajectory":  # as for min_valid_fraction: no gaps inside a clip
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
        shortfall = join_notes(shortfall, note)
    return views, keep_points, shortfall


def _drop_low_valid(
    views: ViewArrays, fractions: np.ndarray, n_points: int, keep_points: np.ndarray, spec: JobSpec,
    shortfall: str | None,
) -> tuple[ViewArrays, np.ndarray, str | None]:
    """Drop views predicted to see too little surface, and the points left with too few views."""
    vs, ps = spec.views, spec.points
    passing = fractions >= vs.min_valid_fraction
    if vs.mode == "trajectory":  # a frame dropped from inside a clip would make its video jump
        passing = _longest_runs(views.point_idx, passing, vs.trajectory_min_frames)
    views = views.subset(passing)
    n_views = np.bincount(views.point_idx, minlength=n_points)
    kept = keep_points[n_views[keep_points] >= ps.min_views]
    views = views.subset(np.isin(views.point_idx, kept))
    dropped = int((~passing).sum())
    if dropped or len(kept) < len(keep_points):
        cut = " (each clip keeps its longest run of frames above it)" if vs.mode == "trajectory" else ""
        note = (
            f"views.min_valid_fraction {vs.min_valid_fraction} dropped {dropped} views{cut}; "
            f"{len(kept)} of {len(keep_points)} points keep >= {ps.min_views} views"
        )
        shortfall = join_notes(shortfall, note)
    return views, kept, shortfall


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


def _assemble(
    space_name: str,
    salt: bytes,
    cams: np.ndarray,
    source: str,
    camera_spec: CameraSpec,
    sampled: SampledPoints,
    keep_points: np.ndarray,
    views: ViewArrays,
    resolution: int,
    shortfall: str | None,
    notes: list[ClipNote],
) -> SpacePlan:
    cameras = camera_poses(cams, source, camera_spec, salt)
    new_idx = np.full(len(sampled.positions), -1, dtype=np.int64)
    new_idx[keep_points] = np.arange(len(keep_points))
    points = points_of(sampled, keep_points, 0, salt)
    # renumber v within each point after pruning
    pidx = new_idx[views.point_idx]
    order = np.lexsort((views.v, pidx))
    pidx = pidx[order]
    counts = np.bincount(pidx, minlength=len(points)) if len(pidx) else np.zeros(len(points), dtype=np.int64)
    v = np.arange(len(pidx)) - np.repeat(np.cumsum(counts) - counts, counts)
    planned = planned_views(dataclasses.replace(views.subset(order), point_idx=pidx, v=v), resolution)
    # clip notes name the points by their index in the plan (None: dropped)
    clip_notes = tuple(n.as_dict(int(new_idx[n.point]) if new_idx[n.point] >= 0 else None) for n in notes)
    shortfall = join_notes(shortfall, clip_shortfall(clip_notes, len(sampled.positions)))
    return SpacePlan(
        space_name=space_name, cameras=cameras, points=points, views=planned, shortfall=shortfall,
        clip_notes=clip_notes,
    )
