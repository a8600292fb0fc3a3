"""Produce a view's cue files: one render per view, every cue derived from its pass set, so
a view costs one Cycles render however many cues it asks for.

    ctx = make_context(space, view, cues, params)      # nothing rendered yet
    data = produce("depth_zbuffer", ctx)               # renders once, then derives; bytes of the PNG
    files = render_view_cues(space, view, cues, params)  # {cue: bytes} for a whole view

A context built from a cached pass set (ViewContext(view, params, passes=ViewPasses.from_bytes(...))) produces
every render/derived cue without Blender. Plan cues need `plan` (services.core.domain.plan) or a ready
`point_info`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from services.core.domain.cues import closure, require_supported
from services.core.domain.jobspec import CueParams
from services.core.domain.plan import SpacePlan
from services.worker.context import SemanticsUnavailableError, ViewContext
from services.worker.cues import encode, get_impl
from services.worker.cues.registry import cue_value
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import RENDER_PASSES, ViewPose

__all__ = [
    "SemanticsUnavailableError", "ViewContext", "check_cues", "make_context", "produce", "render_passes_for",
    "render_view_cues",
]


def check_cues(cues: Iterable[str], *, has_semantics: bool) -> list[str]:
    """Validate cue names against the registry (UnknownCueError lists the known ones) and the space's
    labels."""
    names = list(dict.fromkeys(cues))
    for name in names:
        get_impl(name)
    require_supported(names, has_semantics=has_semantics, error=SemanticsUnavailableError)
    return names


def render_passes_for(cues: Iterable[str]) -> frozenset[str]:
    """The optional render passes (passes.RENDER_PASSES) that `cues` and the cues they are made from read.

    The internal `passes` cue (the cached pass set) is an input of every render cue in the catalog; it asks
    for every pass only when it is requested itself.
    """
    names = set(cues)
    if "passes" in names:
        return RENDER_PASSES
    return frozenset().union(*(get_impl(c).passes for c in closure(names) if c != "passes"))


def make_context(
    space: SpaceContext | None, view: ViewPose, cues: Iterable[str], params: CueParams | None = None,
    *,
    plan: SpacePlan | None = None, point_info: Mapping[str, object] | None = None,
) -> ViewContext:
    """A ViewContext that renders from `space` on first need, only the passes the cues need."""
    names = check_cues(cues, has_semantics=space.has_semantics if space is not None else True)
    return ViewContext(view, params, space=space, plan=plan, point_info=point_info,
                       render_passes=render_passes_for(names))


# The last JSON value encoded per cue and its bytes: a value shared by several views (the nonfixated dict of a
# point, the same object for each of its views) is encoded once. Kept by identity, so a new value never hits.
_last_json: dict[str, tuple[dict, bytes]] = {}


def produce(cue: str, ctx: ViewContext) -> bytes:
    """The file bytes of `cue` for the view of `ctx` (its inputs computed once per context)."""
    get_impl(cue)
    value = cue_value(ctx, cue)
    t0 = ctx.clock()
    last = _last_json.get(cue)
    if last is not None and last[0] is value:
        data = last[1]
    else:
        data = encode(cue, value, exr_compression=ctx.params.position_compression)
        if isinstance(value, dict):
            _last_json[cue] = (value, data)
    ctx.timings[f"encode:{cue}"] = ctx.clock() - t0
    return data


def render_view_cues(
    space_ctx: SpaceContext, view: ViewPose, cues: Iterable[str], params: CueParams | None = None,
    *,
    plan: SpacePlan | None = None, point_info: Mapping[str, object] | None = None,
) -> dict[str, bytes]:
    """{cue: file bytes} for one view: one Cycles render, then every cue derived from its passes."""
    names = list(dict.fromkeys(cues))
    ctx = make_context(space_ctx, view, names, params, plan=plan, point_info=point_info)
    return {name: produce(name, ctx) for name in names}
