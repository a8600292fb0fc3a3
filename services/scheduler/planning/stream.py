"""A space's plan in chunks of whole points, so that planning never holds the whole plan (bounded memory).

This is the one planner of the specs that plan in chunks (camera modes object, generate and provided;
wide_baseline views; no nonfixated pruning; no views.min_valid_fraction filter; no photo-textured rgb):
`make_plan` of such a spec collects its chunks. What stays in memory is the cameras, the sampled points
(positions, normals, the cameras that see each) and one chunk of about `chunk_views` views; the cameras come
with the first chunk, every point with all of its views.

The draws are those of a plan made in one piece (views.wide_baseline): all the per-point camera choices,
then all the fovs, then all the rolls. A first pass over the points replays the camera choices and keeps the
generator's state at each chunk's start; a chunk's fov and roll draws come from copies of the generator
advanced to the chunk's first view (PCG64 `advance`: one step per double).
"""

from __future__ import annotations

import copy
import dataclasses
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import SpacePlan
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
from services.scheduler.planning.points import SampledPoints
from services.scheduler.planning.views import cap_views, fraction_summary, valid_fractions, wide_baseline_span
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

    def collect(self) -> SpacePlan:
        """The whole plan: every chunk joined."""
        chunks = list(self)
        assert self.whole is not None  # set once the chunks are spent
        return dataclasses.replace(self.whole, cameras=tuple(c for k in chunks for c in k.cameras),
                                   points=tuple(p for k in chunks for p in k.points),
                                   views=tuple(v for k in chunks for v in k.views))


def stream_plan(space: LoadedSpace, spec: JobSpec, rng: np.random.Generator, space_name: str,
                chunk_views: int | None, timings: dict[str, float] | None = None) -> PlanChunks:
    """The plan of `space` in chunks of about `chunk_views` views (None: one chunk); `timings` as
    make_plan's."""
    out = PlanChunks(iter(()))
    out.chunks = _stream(space, spec, rng, space_name, chunk_views or sys.maxsize, out, timings)
    return out


def cut_plan(plan: SpacePlan, chunk_views: int) -> PlanChunks:
    """A plan made whole, as chunks."""
    out = PlanChunks(iter(()))
    out.chunks = _cut(plan, chunk_views, out)
    return out


def _bounds(views_per_point: np.ndarray, chunk_views: int) -> list[tuple[int, int]]:
    """[(first point, end point)] of consecutive chunks of about `chunk_views` views, each at least one
    point."""
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
    per_point = np.bincount(
        np.fromiter((v.point_idx for v in plan.views), dtype=np.int64, count=len(plan.views)),
        minlength=len(plan.points),
    )
    first_view = np.concatenate([[0], np.cumsum(per_point)])
    out.whole = dataclasses.replace(plan, cameras=(), points=(), views=())
    for i, (lo, hi) in enumerate(_bounds(per_point, chunk_views)):
        yield dataclasses.replace(plan, cameras=plan.cameras if i == 0 else (), points=plan.points[lo:hi],
                                  views=plan.views[int(first_view[lo]):int(first_view[hi])])


def _stream(space: LoadedSpace, spec: JobSpec, rng: np.random.Generator, space_name: str, chunk_views: int,
            out: PlanChunks, timings: dict[str, float] | None) -> Iterator[SpacePlan]:
    t0 = time.perf_counter()
    stamp = {"assemble": 0.0}
    q = MeshQueries(space.mesh)
    salt = rng.bytes(16)
    cams, source, _orbit = place_cameras(space, spec.cameras, q, rng)
    stamp["cameras"] = (t1 := time.perf_counter()) - t0
    sampled = sample_space_points(q, cams, spec, space_name, rng)
    stamp["points"] = time.perf_counter() - t1
    # first pass: each point's number of views, and the generator's state where each chunk starts
    ps = spec.points
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
    cameras = camera_poses(cams, source, spec.cameras, salt)
    stamp["views"] = time.perf_counter() - t1 - stamp["points"]  # the first pass
    for i, (lo, hi) in enumerate(bounds):
        t2 = time.perf_counter()
        views = wide_baseline_span(sampled.positions, sampled.normals, sampled.visible, cams, spec.views,
                                   ps.max_views, (lo, hi), (starts[i], fov_rng, roll_rng))
        lo_view = int(first_view[lo])
        mine = sample[(sample >= lo_view) & (sample < lo_view + len(views))] - lo_view
        probed.append(valid_fractions(q, views.subset(mine), spec.params.max_depth_m))
        stamp["views"] += (t3 := time.perf_counter()) - t2
        chunk = SpacePlan(space_name=space_name, cameras=cameras if i == 0 else (),
                          points=points_of(sampled, range(lo, hi), lo, salt),
                          views=planned_views(views, spec.views.resolution))
        stamp["assemble"] += time.perf_counter() - t3
        yield chunk
    summary = fraction_summary(np.concatenate(probed) if probed else np.zeros(0), 0.0)
    summary["sampled_of"] = n_views
    out.whole = SpacePlan(space_name=space_name, cameras=(), points=(), views=(),
                          shortfall=join_notes(sampled.shortfall), valid_fraction=summary)
    if timings is not None:
        timings.update(stamp, rays=float(q.rays), total=sum(stamp.values()))  # not the consumer's time


def _copy(rng: np.random.Generator) -> np.random.Generator:
    """An independent generator at `rng`'s current state."""
    return copy.deepcopy(rng)


def _chunk_states(sampled: SampledPoints, bounds: list[tuple[int, int]], max_views: int | None,
                  rng: np.random.Generator) -> list[np.random.Generator]:
    """Copies of the generator at each chunk's first point, replaying the camera choices; `rng` ends past them
    all (where the fovs are drawn)."""
    if not isinstance(rng.bit_generator, np.random.PCG64):
        raise TypeError(
            f"chunked planning needs a PCG64 generator (space_rng), not {type(rng.bit_generator)}"
        )
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
