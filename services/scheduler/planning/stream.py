"""A space's plan in chunks of whole points, so that planning never holds the whole plan (bounded memory).

`plan_chunks` gives the same plan as `make_plan`, point by point and view by view, in chunks of about
`chunk_views` views: the cameras come with the first chunk, every point with all of its views.

For the common specs (camera modes object, generate and provided; wide_baseline views; no nonfixated pruning;
no views.min_valid_fraction filter; no photo-textured rgb) the views are made chunk by chunk: what stays in
memory is the cameras, the sampled points (positions, normals, the cameras that see each) and one chunk. The
random draws are those of `make_plan`: a first pass over the points replays the per-point camera choices and
keeps the generator's state at each chunk's start; the fov and roll draws of a chunk are taken from copies of
the generator advanced to the chunk's first view (PCG64 `advance`: one step per double). The other specs are
planned whole by `make_plan` and then cut into chunks (their memory is bounded by the planning budget only).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import CameraPose, PlannedView, PointOfInterest, SpacePlan
from services.core.domain.plan_budget import plans_in_chunks
from services.core.ingest.loading import LoadedSpace
from services.scheduler.planning import (
    VALID_REPORT_VIEWS,
    check_enough_cameras,
    join_notes,
    make_plan,
    place_cameras,
    plan_uuid,
)
from services.scheduler.planning.points import SampledPoints, sample_points
from services.scheduler.planning.views import (
    ViewArrays,
    cap_views,
    fraction_summary,
    look_at_batch,
    obliqueness,
    truncated_normal,
    valid_fractions,
)
from services.scheduler.planning.visibility import MeshQueries


@dataclass
class PlanChunks:
    """Iterate for the chunks (SpacePlans of some points and all their views); afterwards `whole` holds the
    plan's own fields (shortfall, valid_fraction, clip notes, capture) and `views` the number of views."""

    chunks: Iterator[SpacePlan]
    whole: SpacePlan | None = None
    views: int = 0
    points: int = 0
    cameras: int = 0

    def __iter__(self) -> Iterator[SpacePlan]:
        for chunk in self.chunks:
            self.views += len(chunk.views)
            self.points += len(chunk.points)
            self.cameras += len(chunk.cameras)
            yield chunk


def plan_chunks(space: LoadedSpace, spec: JobSpec, rng: np.random.Generator, space_name: str,
                chunk_views: int) -> PlanChunks:
    """The plan of `space` in chunks of whole points holding about `chunk_views` views (at least one point)."""
    if not plans_in_chunks(spec):  # planned whole, then cut
        plan = make_plan(space, spec, rng, space_name)
        out = PlanChunks(iter(()))
        out.chunks = _cut(plan, chunk_views, out)
        return out
    out = PlanChunks(iter(()))
    out.chunks = _stream(space, spec, rng, space_name, chunk_views, out)
    return out


def cut_plan(plan: SpacePlan, chunk_views: int) -> PlanChunks:
    """A whole plan (a test's plan function) as chunks."""
    out = PlanChunks(iter(()))
    out.chunks = _cut(plan, chunk_views, out)
    return out


def _bounds(views_per_point: np.ndarray, chunk_views: int) -> list[tuple[int, int]]:
    """[(first point, end point)] of consecutive chunks of about `chunk_views` views, each at least one point."""
    bounds, start, total = [], 0, 0
    for p, n in enumerate(views_per_point.tolist()):
        if total and total + n > chunk_views:
            bounds.append((start, p))
            start, total = p, 0
        total += n
    if start < len(views_per_point) or not bounds:
        bounds.append((start, len(views_per_point)))
    return bounds


def _cut(plan: SpacePlan, chunk_views: int, out: PlanChunks) -> Iterator[SpacePlan]:
    per_point = np.bincount(np.fromiter((v.point_idx for v in plan.views), dtype=np.int64, count=len(plan.views)),
                            minlength=len(plan.points))
    first_view = np.concatenate([[0], np.cumsum(per_point)])
    out.whole = dataclasses.replace(plan, cameras=(), points=(), views=())
    for i, (lo, hi) in enumerate(_bounds(per_point, chunk_views)):
        yield dataclasses.replace(plan, cameras=plan.cameras if i == 0 else (), points=plan.points[lo:hi],
                                  views=plan.views[int(first_view[lo]):int(first_view[hi])])


def _stream(space: LoadedSpace, spec: JobSpec, rng: np.random.Generator, space_name: str, chunk_views: int,
            out: PlanChunks) -> Iterator[SpacePlan]:
    q = MeshQueries(space.mesh)
    salt = rng.bytes(16)
    cams, source, _orbit = place_cameras(space, spec.cameras, q, rng)
    ps = spec.points
    check_enough_cameras(len(cams), spec, space_name)
    count = ps.count if ps.count is not None else max(1, int(round(ps.per_camera * len(cams))))
    sampled = sample_points(q, cams, ps, count, rng)
    # first pass: each point's number of views, and the generator's state where each chunk starts
    cap = ps.max_views if ps.max_views is not None else len(cams)
    per_point = np.array([min(len(c), cap) for c in sampled.visible], dtype=np.int64)
    bounds = _bounds(per_point, chunk_views)
    n_views = int(per_point.sum())
    first_view = np.concatenate([[0], np.cumsum(per_point)])
    starts = _chunk_states(sampled, bounds, ps.max_views, rng)
    fov_rng, roll_rng = _copy(rng), _copy(rng)
    roll_rng.bit_generator.advance(n_views)  # type: ignore[attr-defined]  # PCG64: the rolls follow every fov
    sample = np.unique(np.linspace(0, n_views - 1, min(n_views, VALID_REPORT_VIEWS)).astype(np.int64))
    probed: list[np.ndarray] = []
    given = [p.uuid for p in spec.cameras.poses] if source == "provided" and spec.cameras.poses else [None] * len(cams)
    cameras = tuple(CameraPose(idx=i, position=cams[i], source=source, uuid=given[i] or plan_uuid(salt, "camera", i))
                    for i in range(len(cams)))
    for i, (lo, hi) in enumerate(bounds):
        views = _chunk_views(sampled, cams, lo, hi, spec, starts[i], fov_rng, roll_rng)
        lo_view = int(first_view[lo])
        mine = sample[(sample >= lo_view) & (sample < lo_view + len(views))] - lo_view
        probed.append(valid_fractions(q, views.subset(mine), spec.params.max_depth_m))
        yield SpacePlan(space_name=space_name, cameras=cameras if i == 0 else (),
                        points=_points(sampled, lo, hi, salt), views=_planned(views, spec.views.resolution))
    summary = fraction_summary(np.concatenate(probed) if probed else np.zeros(0), 0.0)
    summary["sampled_of"] = n_views
    out.whole = SpacePlan(space_name=space_name, cameras=(), points=(), views=(),
                          shortfall=join_notes(sampled.shortfall), valid_fraction=summary)


def _copy(rng: np.random.Generator) -> np.random.Generator:
    """An independent generator at `rng`'s current state."""
    return copy.deepcopy(rng)


def _chunk_states(sampled: SampledPoints, bounds: list[tuple[int, int]], max_views: int | None,
                  rng: np.random.Generator) -> list[np.random.Generator]:
    """Copies of the generator at each chunk's first point, replaying the camera choices; `rng` ends past them all
    (where make_plan draws the fovs)."""
    if not isinstance(rng.bit_generator, np.random.PCG64):
        raise TypeError(f"chunked planning needs a PCG64 generator (space_rng), not {type(rng.bit_generator)}")
    starts: list[np.random.Generator] = []
    chunk = 0
    for p, visible in enumerate(sampled.visible):
        if chunk < len(bounds) and p == bounds[chunk][0]:
            starts.append(_copy(rng))
            chunk += 1
        cap_views(visible, max_views, rng)
    while len(starts) < len(bounds):  # no points at all: one empty chunk
        starts.append(_copy(rng))
    return starts


def _chunk_views(sampled: SampledPoints, cams: np.ndarray, lo: int, hi: int, spec: JobSpec,
                 chunk_rng: np.random.Generator, fov_rng: np.random.Generator,
                 roll_rng: np.random.Generator) -> ViewArrays:
    """wide_baseline's views of points lo..hi-1, with make_plan's draws."""
    vs, ps = spec.views, spec.points
    chosen = [cap_views(sampled.visible[p], ps.max_views, chunk_rng) for p in range(lo, hi)]
    P = np.repeat(np.arange(lo, hi, dtype=np.int64), [len(c) for c in chosen])
    C = np.concatenate(chosen) if chosen else np.zeros(0, dtype=np.int64)
    V = np.concatenate([np.arange(len(c), dtype=np.int64) for c in chosen]) if chosen else np.zeros(0, dtype=np.int64)
    n = len(P)
    fov = truncated_normal(fov_rng, np.radians(vs.fov_mean_deg), np.radians(vs.fov_std_deg),
                           np.radians(vs.fov_min_deg), np.radians(vs.fov_max_deg), n)
    rmax = np.radians(vs.roll_max_deg)
    roll = roll_rng.uniform(-rmax, rmax, n)
    pos, nrm = sampled.positions, sampled.normals
    W = look_at_batch(cams[C], pos[P], roll) if n else np.zeros((0, 4, 4))
    obl = obliqueness(nrm[P], pos[P], cams[C]) if n else np.zeros(0)
    return ViewArrays(P, V, C, W, fov, roll, obl, np.ones(n, dtype=bool))


def _points(sampled: SampledPoints, lo: int, hi: int, salt: bytes) -> tuple[PointOfInterest, ...]:
    return tuple(PointOfInterest(idx=p, position=sampled.positions[p], normal=sampled.normals[p],
                                 uuid=plan_uuid(salt, "point", p), camera_idxs=tuple(sampled.visible[p].tolist()))
                 for p in range(lo, hi))


def _planned(views: ViewArrays, resolution: int) -> tuple[PlannedView, ...]:
    return tuple(
        PlannedView(point_idx=int(views.point_idx[i]), v=int(views.v[i]), camera_idx=int(views.camera_idx[i]),
                    world_to_camera=views.world_to_camera[i], fov=float(views.fov[i]), roll=float(views.roll[i]),
                    resolution=int(resolution), obliqueness=float(views.obliqueness[i]),
                    in_sight=bool(views.in_sight[i]))
        for i in range(len(views)))
