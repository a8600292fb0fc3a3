"""Produce a view's cue files: one render per view, every cue derived from its pass set (DESIGN.md section 6).

    ctx = make_context(space, view, cues, params)      # nothing rendered yet
    data = produce("depth_zbuffer", ctx)               # renders once, then derives; bytes of the PNG
    files = render_view_cues(space, view, cues, params)  # {cue: bytes} for a whole view

A context built from a cached pass set (ViewContext(view, params, passes=ViewPasses.from_bytes(...))) produces
every render/derived cue without Blender. Plan cues need `plan` (services.core.plan) or a ready `point_info`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Any

from services.core.cues import require_supported
from services.core.jobspec import CueParams
from services.worker.context import SemanticsUnavailableError, ViewContext
from services.worker.cues import encode, get_impl
from services.worker.cues.registry import cue_value
from services.worker.space_cache import SpaceContext

__all__ = ["SemanticsUnavailableError", "ViewContext", "check_cues", "make_context", "produce", "render_view_cues"]


def check_cues(cues: Iterable[str], *, has_semantics: bool) -> list[str]:
    """Validate cue names against the registry (UnknownCueError lists the known ones) and the space's labels."""
    names = list(dict.fromkeys(cues))
    for name in names:
        get_impl(name)
    require_supported(names, has_semantics=has_semantics, error=SemanticsUnavailableError)
    return names


def make_context(space: SpaceContext | None, view: Any, cues: Iterable[str], params: CueParams | None = None, *,
                 plan: Any = None, point_info: dict | None = None) -> ViewContext:
    """A ViewContext that renders from `space` on first need; curvature is rendered only if a cue needs it."""
    names = check_cues(cues, has_semantics=space.has_semantics if space is not None else True)
    return ViewContext(view, params, space=space, plan=plan, point_info=point_info,
                       render_curvature=bool({"principal_curvature", "passes"} & set(names)))


def produce(cue: str, ctx: ViewContext) -> bytes:
    """The file bytes of `cue` for the view of `ctx` (its inputs computed once per context)."""
    get_impl(cue)
    value = cue_value(ctx, cue)
    t0 = time.perf_counter()
    data = encode(cue, value)
    ctx.timings[f"encode:{cue}"] = time.perf_counter() - t0
    return data


def render_view_cues(space_ctx: SpaceContext, view: Any, cues: Iterable[str], params: CueParams | None = None,
                     *, plan: Any = None, point_info: dict | None = None) -> dict[str, bytes]:
    """{cue: file bytes} for one view: one Cycles render, then every cue derived from its passes."""
    names = list(dict.fromkeys(cues))
    ctx = make_context(space_ctx, view, names, params, plan=plan, point_info=point_info)
    return {name: produce(name, ctx) for name in names}
