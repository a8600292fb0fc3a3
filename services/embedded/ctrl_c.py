"""A Ctrl-C the generate loop cannot lose.

Python raises KeyboardInterrupt wherever the main thread happens to be. Inside a finalizer (a weakref
callback, a __del__: SQLAlchemy runs one for every ORM object collected) it is printed as "Exception ignored"
and dropped, and the run went on to finish with exit 0 (seen in CI). While `latched_sigint()` is active,
SIGINT still raises at once, and is also remembered: the loop calls `raise_if_interrupted()` each turn and
raises it again.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

_interrupted = False


def _on_sigint(signum: int, frame: FrameType | None) -> None:
    global _interrupted
    _interrupted = True
    raise KeyboardInterrupt


@contextmanager
def latched_sigint() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt and is remembered until the block ends (main thread only: elsewhere no
    handler can be installed, and Python's own stays). Inside an outer block this one changes nothing: what
    the outer one remembered stays remembered."""
    global _interrupted
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is _on_sigint
    ):
        yield
        return
    previous = signal.signal(signal.SIGINT, _on_sigint)
    _interrupted = False
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _interrupted = False


def raise_if_interrupted() -> None:
    """Raise the KeyboardInterrupt a finalizer swallowed (a no-op when none came)."""
    if _interrupted:
        raise KeyboardInterrupt
