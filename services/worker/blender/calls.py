"""Calls into Blender, marked so that a signal handler knows when it runs inside one.

While Blender's C code runs a render it calls back into Python (Cycles' engine is a Python class). A signal
handler that raises there (SIGTERM's SystemExit) does not unwind our stack: Blender's C code hands the exception
to PyErr_Print, which exits the process through Blender's C++ destructors, printing their leak report and at
times deadlocking in them, so the process only ends when its parent kills it. A handler that finds
`inside_blender()` ends the process itself instead (os._exit). This module imports nothing of Blender.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

_depth = 0  # calls into Blender in progress in this process (its main thread makes them)


@contextlib.contextmanager
def in_blender() -> Iterator[None]:
    """Mark a call into Blender (a render) for `inside_blender`."""
    global _depth
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1


def inside_blender() -> bool:
    """Whether a call marked with `in_blender` is in progress (an exception raised now would reach Blender)."""
    return _depth > 0
