"""What one job may plan: a memory and a time budget, checked before any planning starts.

Most specs are planned in chunks (`plans_in_chunks`: services.scheduler.planning.stream): the planner holds
the cameras, the sampled points (each with the cameras that see it) and one chunk of OMNIDATA_PLAN_CHUNK_VIEWS
views, so its peak grows with the points and cameras, not with the views: PLAN_BASE_MB + points x
(PLAN_BYTES_PER_POINT + PLAN_BYTES_PER_POINT_CAMERA x cameras) + chunk views x PLAN_BYTES_PER_VIEW.
The other specs (capture cameras, trajectories, nonfixated pruning, a min_valid_fraction filter,
photo-textured rgb) are planned whole: their plan lives in the planner's memory while it is built (cameras,
points, views with their poses, compiled tasks, the rows and the plan JSON written for the workers), so its
peak grows with the number of views. The upper estimate of a spec's views (`JobSpec.views_upper_bound`) times
the measured peak bytes per view must fit in `OMNIDATA_PLAN_MEMORY_MB`, the address-space limit the planner
process runs under; a spec that cannot is refused when the job is created (HTTP 422 naming the budget) instead
of failing, or stalling a machine, later. The same for time: views times the measured seconds per view must
fit in `OMNIDATA_PLAN_TIMEOUT_S`, after which the planner process is ended.
"""

from __future__ import annotations

from services.core.domain.jobspec import JobSpec

# Measured peak planner RSS per planned view, with the cues' tasks and persistence included
# (bench/plan/planner.py:
# object mode on the bunny, 200k views, all default cues), rounded up; plus the process's fixed part (numpy,
# trimesh, embree, SQLAlchemy, the loaded mesh).
PLAN_BYTES_PER_VIEW = 6_000
PLAN_BASE_MB = 400
# measured 0.8 ms per view (bench/plan/planner.py, loaded 2-core machine), rounded up
PLAN_SECONDS_PER_VIEW = 0.002


class PlanOverBudget(ValueError):
    """A spec whose plan could need more memory than the planning budget allows."""


PLAN_BYTES_PER_POINT = 512  # a sampled point: position, normal, its array of cameras, the sampling's rows
PLAN_BYTES_PER_POINT_CAMERA = 16  # per camera that may see it (visibility row, camera index)
DEFAULT_CHUNK_VIEWS = 20_000  # OMNIDATA_PLAN_CHUNK_VIEWS' default


def plans_in_chunks(spec: JobSpec) -> bool:
    """Whether the scheduler plans `spec` chunk by chunk (bounded memory) rather than whole."""
    vs = spec.views
    return (spec.cameras.mode in ("object", "generate", "provided") and vs.mode == "wide_baseline"
            and not vs.nonfixated_pruning and vs.min_valid_fraction == 0 and not spec.uses_photos()
            and vs.fov_quantiles_deg is None and vs.pitch_quantiles_deg is None
            and vs.roll_quantiles_deg is None)  # steered: planned whole


def plan_memory_estimate_mb(spec: JobSpec, chunk_views: int = DEFAULT_CHUNK_VIEWS) -> int:
    """Upper estimate of the planner's peak memory for a spec, in MB (per space: spaces are planned one by
    one)."""
    views, points, _per_point, _what = spec.plan_size()
    if plans_in_chunks(spec):
        cameras = spec.camera_count_bound()
        held = points * (PLAN_BYTES_PER_POINT + PLAN_BYTES_PER_POINT_CAMERA * cameras)
        return PLAN_BASE_MB + -(-(held + min(views, chunk_views) * PLAN_BYTES_PER_VIEW) // 2**20)
    return PLAN_BASE_MB + -(-views * PLAN_BYTES_PER_VIEW // 2**20)


def bound_is_known(spec: JobSpec) -> bool:
    """Whether the spec's knobs bound its views closely enough to judge it before planning.

    Object cameras, given poses or an explicit points.max_views fix the views per point. Cameras generated
    in free space with no max_views are bounded only by cameras.max_count (1,000 by default, five million
    views for the default spec), while a real room gives each point the few cameras that see it; such specs
    are capped while they plan instead (the planner process's memory limit and time budget).
    """
    return spec.cameras.mode != "generate" or spec.points.max_views is not None


def check_plan_budget(spec: JobSpec, *, memory_mb: int, timeout_s: float | None = None,
                      chunk_views: int = DEFAULT_CHUNK_VIEWS) -> None:
    """Raise PlanOverBudget, naming the budget and the knobs to lower, when the spec's plan could exceed
    it."""
    if not bound_is_known(spec):
        return
    need = plan_memory_estimate_mb(spec, chunk_views)
    views = spec.views_upper_bound()
    if timeout_s is not None and views * PLAN_SECONDS_PER_VIEW > timeout_s:
        raise PlanOverBudget(
            f"this spec could plan {views:,} views per space, about "
            f"{views * PLAN_SECONDS_PER_VIEW:,.0f} s of planning, "
            f"above the planning time budget of {timeout_s:,.0f} s (OMNIDATA_PLAN_TIMEOUT_S; about "
            f"{int(timeout_s / PLAN_SECONDS_PER_VIEW):,} views): lower points.count or "
            "points.max_views, or split the job"
        )
    if need > memory_mb:
        fits = max(0, (memory_mb - PLAN_BASE_MB) * 2**20 // PLAN_BYTES_PER_VIEW)
        raise PlanOverBudget(
            f"this spec could plan {views:,} views per space, needing about {need:,} MB to plan, "
            "above the planning "
            f"budget of {memory_mb:,} MB (OMNIDATA_PLAN_MEMORY_MB; about {fits:,} views): lower "
            "points.count or points.max_views (or views.trajectory_max_frames), or split the job"
        )
