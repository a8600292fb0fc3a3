"""ViewContext: everything one view's cues are computed from, with per-view memoisation of intermediates.

A context holds the view geometry, the cue parameters, and either a ready pass set (loaded from the `passes`
cache) or the space to render it from (rendered at most once, on first use). Intermediate arrays (valid mask,
camera-space normals, euclidean distance, superpixels...) and cue values are memoised, so derived cues compute
their inputs from the passes once per view.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, TypeVar, cast

from services.core.domain.jobspec import CueParams
from services.worker.passes import OPTIONAL_ARRAYS, RENDER_PASSES, ViewGeometry, ViewPasses, ViewPose

if TYPE_CHECKING:
    from services.core.domain.plan import SpacePlan
    from services.worker.inputs.space_cache import SpaceContext

T = TypeVar("T")


class SemanticsUnavailableError(ValueError):
    """A semantic cue was asked of a view whose space has no face labels."""


class ViewContext:
    """Inputs and memo of one view. `view` is a ViewGeometry or anything with
    world_to_camera/fov/resolution."""

    def __init__(
        self, view: ViewPose | None, params: CueParams | None = None,
        *,
        passes: ViewPasses | None = None, space: SpaceContext | None = None, plan: SpacePlan | None = None,
        point_info: Mapping[str, object] | None = None, render_passes: frozenset[str] = RENDER_PASSES,
    ):
        self.view = view
        if view is not None:
            self.geometry = ViewGeometry.of(view)
        elif passes is not None:
            self.geometry = passes.geometry
        else:
            raise ValueError("a view context needs a view or a pass set")
        self.params = params or CueParams()
        self.space = space
        self.plan = plan
        self.point_info_override = point_info
        # optional passes rendered (passes.RENDER_PASSES); colour, depth always
        self.render_passes = render_passes
        self._passes = passes
        self._memo: dict[str, object] = {}
        self.timings: dict[str, float] = {}  # exclusive seconds per cue value / intermediate / "render"
        # The clock of `timings`: wall time; a benchmark on a shared machine may set time.process_time (CPU
        # seconds of this process, all threads), which other processes' load does not inflate.
        self.clock: Callable[[], float] = time.perf_counter
        self._nested: list[float] = []

    @property
    def passes(self) -> ViewPasses:
        """The view's pass set, rendering it from the space on first use (one render per view)."""
        if self._passes is None:
            if self.space is None:
                raise RuntimeError("this view has neither a pass set nor a space to render it from")
            space = self.space
            self._passes = self.memo(
                "render", lambda: space.render(self.geometry, self.params, passes=self.render_passes)
            )
        return self._passes

    def nbytes(self) -> int:
        """Bytes of the arrays this context holds (pass set, memoised values): what keeping it in a cache
        costs."""
        values: list[object] = list(self._memo.values())
        if self._passes is not None:
            values += [getattr(self._passes, n) for n in ("depth_z", "rgb", *OPTIONAL_ARRAYS)]
        flat = [x for v in values for x in (v if isinstance(v, tuple | list) else (v,))]
        return sum(x.nbytes if hasattr(x, "nbytes") else len(x) if isinstance(x, bytes) else 0 for x in flat)

    @property
    def resolution(self) -> int:
        """Square image size in pixels."""
        return self.geometry.resolution

    def memo(self, key: str, fn: Callable[[], T]) -> T:
        """Compute `fn()` once per view under `key` and record how long it took."""
        if key not in self._memo:
            # Exclusive timings: time spent in nested memo entries (e.g. the render) is booked to them.
            t0 = self.clock()
            self._nested.append(0.0)
            try:
                self._memo[key] = fn()
            finally:
                nested = self._nested.pop()
                dt = self.clock() - t0
                self.timings[key] = dt - nested
                if self._nested:
                    self._nested[-1] += dt
        return cast(T, self._memo[key])  # what fn() returned for this key
