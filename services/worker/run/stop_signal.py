"""A stop raised by a signal handler while native code runs can come back wrapped in another exception.

SIGTERM's SystemExit (the embedded pool's handler, Celery's pool's) raised while a compiled (numba) kernel is
being called comes back from that call as SystemError("... returned a result with an exception set") caused by
the exit. A worker that recorded it as the task's failure would lose its stop and go on working until it was
killed: `reraise_stop` raises the stop again, so the worker unwinds and leaves as it does from anywhere else.
"""

from __future__ import annotations

_STOPS = (SystemExit, KeyboardInterrupt)


def stop_within(exc: BaseException) -> SystemExit | KeyboardInterrupt | None:
    """The stop that `exc` is, or that caused it (along __cause__), else None."""
    seen: BaseException | None = exc
    for _ in range(16):  # a cause chain is short; a cycle must not hang the worker
        if seen is None:
            return None
        if isinstance(seen, _STOPS):
            return seen
        seen = seen.__cause__
    return None


def reraise_stop(exc: BaseException) -> None:
    """Raise the stop within `exc`, if any (call it first in an `except Exception` that records a failure)."""
    stop = stop_within(exc)
    if stop is not None:
        raise stop
