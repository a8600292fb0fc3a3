"""Plan cues: JSON made from the plan alone by services.core.plan (the executor only encodes them).

A context may carry a ready `point_info` dict (e.g. read back from the database) instead of the plan.
"""

from __future__ import annotations

from typing import Any

from services.worker.context import ViewContext
from services.worker.cues.registry import cue_value, register


def _need_plan(ctx: ViewContext, cue: str) -> Any:
    if ctx.plan is None:
        raise RuntimeError(f"cue {cue!r} is made from the plan, and this view context has no plan")
    return ctx.plan


@register("point_info")
def point_info(ctx: ViewContext) -> dict:
    """Omnidata point_info keys plus K, world_to_camera and conventions (services.core.plan.point_info)."""

    def compute() -> dict:
        if ctx.point_info_override is not None:
            return dict(ctx.point_info_override)
        from services.core import plan as plan_mod

        return plan_mod.point_info(_need_plan(ctx, "point_info"), ctx.view)

    return ctx.memo("point_info", compute)


@register("nonfixated")
def nonfixated(ctx: ViewContext) -> dict:
    """Per point: pixel positions of the other points visible in each of its views."""
    from services.core import plan as plan_mod

    return plan_mod.nonfixated(_need_plan(ctx, "nonfixated"), int(ctx.view.point_idx))


@register("vanishing_points")
def vanishing_points(ctx: ViewContext) -> dict:
    """Image-space and Gaussian-sphere vanishing points of the world axes, from point_info."""
    from services.core import plan as plan_mod

    return plan_mod.vanishing_points(cue_value(ctx, "point_info"))
