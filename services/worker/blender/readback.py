"""Reading a Cycles render's passes from memory, not from an EXR written and read back.

Cycles is a Python RenderEngine (the add-on's `CyclesRender`): when its `render` returns, the engine's render
result still holds every pass of the view layer as float32 pixels. `install` wraps that method once per
process; inside `capture()` the wrapper copies each pass with `foreach_get` into buffers reused from view to
view (the float32 values the EXR writer stores: tests/worker/blender/test_pass_identity.py), and outside it
does nothing, so other renders (the benchmarks' floor) pay nothing. It spares the EXR's write and read
(bench/results/passes_cost.json, "ab").

Blender's pixel rows go bottom-up: the channels handed out are row-flipped views (row 0 = top, as in the EXR).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np

_ATTR = "_omnidata_readback"
_CHANNELS = {4: "RGBA", 3: "XYZ", 2: "XY"}  # the EXR writer's names; a one-channel pass goes by its own

_target: dict[str, np.ndarray] | None = None  # armed: channel name -> view, filled by the wrapped render
_buffers: dict[tuple[str, int], np.ndarray] = {}


def install() -> bool:
    """Wrap the Cycles engine's render method (once); False when the add-on offers none to wrap."""
    try:
        import cycles
    except ImportError:
        return False
    engine = getattr(cycles, "CyclesRender", None)
    render = getattr(engine, "render", None)
    if engine is None or render is None:
        return False
    if getattr(render, _ATTR, False):
        return True

    def wrapped(self: Any, depsgraph: Any) -> None:
        render(self, depsgraph)
        if _target is not None:
            _copy(self.get_result(), _target)

    setattr(wrapped, _ATTR, True)
    engine.render = wrapped
    return True


@contextlib.contextmanager
def capture() -> Iterator[dict[str, np.ndarray]]:
    """Arm the wrapper for the renders inside: yields channel name (`<layer>.<pass>[.<channel>]`, as in the
    EXR) -> float32 H x W view, filled when the render returns; the views' buffers are reused by the next
    capture, so decode them first."""
    global _target
    channels: dict[str, np.ndarray] = {}
    _target = channels
    try:
        yield channels
    finally:
        _target = None


def _copy(result: Any, into: dict[str, np.ndarray]) -> None:
    w, h = result.resolution_x, result.resolution_y
    for layer in result.layers:
        for p in layer.passes:
            n = p.channels
            buf = _buffers.get((p.name, n))
            if buf is None or buf.size != w * h * n:
                buf = _buffers[(p.name, n)] = np.empty(w * h * n, np.float32)
            p.rect.foreach_get(buf)
            rows = buf.reshape(h, w, n)[::-1]
            if n == 1:
                into[f"{layer.name}.{p.name}"] = rows[..., 0]
            else:
                into.update({f"{layer.name}.{p.name}.{c}": rows[..., i] for i, c in enumerate(_CHANNELS[n])})
