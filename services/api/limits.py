"""A capacity limiter for worker threads, made on first use (anyio builds limiters inside a running event
loop)."""

from __future__ import annotations

import anyio


class LazyLimiter:
    """At most `slots` threads at once for the work run under it (uploads' mesh checks, event-stream
    polls)."""

    def __init__(self, slots: int) -> None:
        self.slots = slots
        self._limiter: anyio.CapacityLimiter | None = None

    def get(self) -> anyio.CapacityLimiter:
        """The limiter (made on first use)."""
        if self._limiter is None:
            self._limiter = anyio.CapacityLimiter(self.slots)
        return self._limiter
