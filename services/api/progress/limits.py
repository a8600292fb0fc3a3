"""Bounds on server-sent event streams: open streams per tenant, and threads their polls may use at once.

A stream holds no thread between polls, but each poll (a short database read) runs in a worker thread; with
the default pool shared by every synchronous route, a few hundred streams polling twice a second left the
other routes waiting for a thread. Polls get their own small limiter instead, and a tenant may hold at most
`OMNIDATA_SSE_MAX_PER_TENANT` streams (one more is answered 429 with a message and Retry-After).
"""

from __future__ import annotations

import anyio

from services.api.limits import LazyLimiter
from services.core.domain.errors import TooManyRequests


class TooManyStreams(TooManyRequests):
    """A tenant already holds as many event streams as allowed (429: one closes when its client goes)."""


class StreamLimits:
    """Open streams per tenant (counted on the event loop: no lock needed) and the poll threads' limiter."""

    def __init__(self, per_tenant: int, poll_threads: int) -> None:
        self.per_tenant = per_tenant
        self.open: dict[str, int] = {}
        self._polls = LazyLimiter(poll_threads)

    @property
    def limiter(self) -> anyio.CapacityLimiter:
        """The limiter every SSE poll runs under."""
        return self._polls.get()

    def acquire(self, tenant: str) -> None:
        """Count one more stream of `tenant`, or raise TooManyStreams."""
        n = self.open.get(tenant, 0)
        if n >= self.per_tenant:
            raise TooManyStreams(
                f"too many open event streams: {n} of at most {self.per_tenant} per tenant "
                "(OMNIDATA_SSE_MAX_PER_TENANT); close one, or follow all your jobs with one /events stream"
            )
        self.open[tenant] = n + 1

    def release(self, tenant: str) -> None:
        """A stream of `tenant` ended."""
        n = self.open.get(tenant, 0) - 1
        if n > 0:
            self.open[tenant] = n
        else:
            self.open.pop(tenant, None)
