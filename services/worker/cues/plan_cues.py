"""Plan cues registered with the executor: JSON made from the plan alone by services.core.domain.plan_cues.

A context may carry a ready `point_info` dict (e.g. read back from the database) instead of the plan.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping

from services.core.domain import plan_cues
from services.core.domain.plan import PlannedView, SpacePlan
from services.core.domain.plan_cues import Nonfixated, VanishingPoints
from services.worker.context import ViewContext
from services.worker.cues.registry import cue_value, register


def _need_plan(ctx: ViewContext, cue: str) -> SpacePlan:
    if ctx.plan is None:
        raise RuntimeError(f"cue {cue!r} is made from the plan, and this view context has no plan")
    return ctx.plan


def _planned_view(ctx: ViewContext, cue: str) -> PlannedView:
    if not isinstance(ctx.view, PlannedView):
        raise RuntimeError(f"cue {cue!r} is made from the plan, and this view is not one of the plan's views")
    return ctx.view


@register("point_info")
def point_info(ctx: ViewContext) -> Mapping[str, object]:
    """Omnidata point_info keys plus K, world_to_camera and conventions
    (services.core.domain.plan_cues.point_info)."""

    def compute() -> Mapping[str, object]:
        if ctx.point_info_override is not None:
            return dict(ctx.point_info_override)
        return plan_cues.point_info(_need_plan(ctx, "point_info"), _planned_view(ctx, "point_info"))

    return ctx.memo("point_info", compute)


# nonfixated JSON per (plan, point): every view of a point has the same file, and on a room it is megabytes.
_NONFIXATED: weakref.WeakKeyDictionary[SpacePlan, dict[int, Nonfixated]] = weakref.WeakKeyDictionary()
NONFIXATED_POINTS_KEPT = 8


@register("nonfixated")
def nonfixated(ctx: ViewContext) -> Nonfixated:
    """Per point: pixel positions of the other points visible in each of its views (one dict per point,
    shared)."""
    plan = _need_plan(ctx, "nonfixated")
    point = int(_planned_view(ctx, "nonfixated").point_idx)
    per_point = _NONFIXATED.setdefault(plan, {})
    if point not in per_point:
        while len(per_point) >= NONFIXATED_POINTS_KEPT:
            per_point.pop(next(iter(per_point)))
        per_point[point] = plan_cues.nonfixated(plan, point)
    return per_point[point]


@register("vanishing_points")
def vanishing_points(ctx: ViewContext) -> VanishingPoints:
    """Image-space and Gaussian-sphere vanishing points of the world axes, from point_info."""
    info = cue_value(ctx, "point_info")
    if not isinstance(info, Mapping):
        raise TypeError(f"point_info is a JSON object, got {type(info).__name__}")
    return plan_cues.vanishing_points(info)
