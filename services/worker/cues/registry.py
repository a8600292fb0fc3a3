"""The cue registry: each cue family module declares its cues with `@register(name)`, so the
executor finds a cue by its catalog name without a central table to keep in step.

A cue function takes the view's ViewContext and returns the cue's value: a numpy array in the catalog's dtype
and shape (H x W or H x W x 3), a JSON-able dict for plan cues, or bytes for the internal `passes` cue.
Encoding to file bytes is separate (services.worker.cues.encoding) and driven by the catalog entry.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from services.core.domain.cues import CATALOG, Cue, UnknownCueError
from services.worker.passes import RENDER_PASSES

if TYPE_CHECKING:
    from services.worker.context import ViewContext

# an image cue's array, a plan cue's JSON, the `passes` npz
CueValue = np.ndarray | Mapping[str, object] | bytes
CueFn = Callable[["ViewContext"], CueValue]
_Fn = TypeVar("_Fn", bound=CueFn)


@dataclass(frozen=True)
class CueImpl:
    """A registered cue: its catalog entry and the function computing its value from a ViewContext."""

    name: str
    fn: CueFn
    # optional render passes it reads (passes.RENDER_PASSES); depth, rgb always
    passes: frozenset[str] = frozenset()

    @property
    def spec(self) -> Cue:
        """The catalog entry (file type, dtype, channels, inputs)."""
        return CATALOG[self.name]


REGISTRY: dict[str, CueImpl] = {}


def register(name: str, passes: Iterable[str] = ()) -> Callable[[_Fn], _Fn]:
    """Decorator declaring the function of catalog cue `name` (one function per cue) and the optional render
    passes it reads itself (those of the cues it is made from are found through the catalog's inputs)."""
    if name not in CATALOG:
        raise UnknownCueError([name])
    unknown = set(passes) - RENDER_PASSES
    if unknown:
        raise ValueError(
            f"cue {name!r}: unknown render passes {sorted(unknown)}; known: {sorted(RENDER_PASSES)}"
        )

    def deco(fn: _Fn) -> _Fn:
        if name in REGISTRY:
            raise ValueError(
                f"cue {name!r} is registered twice ({REGISTRY[name].fn.__module__}, {fn.__module__})"
            )
        REGISTRY[name] = CueImpl(name, fn, frozenset(passes))
        return fn

    return deco


def get_impl(name: str) -> CueImpl:
    """The registered implementation of `name`; UnknownCueError (listing the known cues) otherwise."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise UnknownCueError([name]) from None


def cue_value(ctx: ViewContext, name: str) -> CueValue:
    """The value of cue `name` for the view of `ctx` (array, dict or bytes), computed once per view.

    Lives here, not on ViewContext, so the context never looks cues up (no run-time cycle); a cue reading
    another cue calls this with a name from its catalog `inputs` (tests/worker/cues check the declarations).
    """
    impl = get_impl(name)
    return ctx.memo(f"cue:{name}", lambda: impl.fn(ctx))


def cue_array(ctx: ViewContext, name: str) -> np.ndarray:
    """`cue_value` of an image cue (rgb, segment_semantic, ...): its array."""
    value = cue_value(ctx, name)
    if not isinstance(value, np.ndarray):
        raise TypeError(f"cue {name!r} is not an image cue (got {type(value).__name__})")
    return value
