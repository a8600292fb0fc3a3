"""Calls into Blender, marked so that a signal handler knows when it runs inside one.

While Blender's C code runs a render it calls back into Python (Cycles' engine is a Python class). A signal
handler that raises there (SIGTERM's SystemExit, from our embedded worker or from Celery's pool) does not
unwind our stack: Blender's C code hands the exception to PyErr_Print, which exits the process through
Blender's C++ destructors, printing their leak report and at times deadlocking in them, so the process only
ends when it is killed. `exit_at_once_inside_blender` wraps a signal's handler so that inside a marked call
the process ends itself (os._exit) instead. This module imports nothing of Blender.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from types import FrameType

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
    """Whether a call marked with `in_blender` is in progress (an exception raised now would reach
    Blender)."""
    return _depth > 0


def exit_at_once_inside_blender(signum: int) -> None:
    """Wrap `signum`'s Python handler: inside a marked Blender call the process ends at once with 128 +
    signum; elsewhere the handler runs as before. Nothing to wrap for SIG_DFL / SIG_IGN (nothing raises), off
    the main thread (handlers are set there only) or when it is wrapped already."""
    previous = signal.getsignal(signum)
    if not callable(previous) or getattr(previous, "wraps_for_blender", False):
        return
    if threading.current_thread() is not threading.main_thread():
        return

    def handler(num: int, frame: FrameType | None) -> None:
        if inside_blender():
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(128 + num)
        previous(num, frame)

    handler.wraps_for_blender = True  # type: ignore[attr-defined]
    signal.signal(signum, handler)
