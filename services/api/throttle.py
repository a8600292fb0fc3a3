"""Per-tenant limits on expensive requests: how many a tenant has under way, and how fast it starts them.

One tenant's 40 concurrent up choices, or 45 manifest readers that stop reading, must not take the threads,
the database connections or the CPU the other tenants need. An expensive route names its kind: `scan` (it
reads a scan in a child process: uploads, registers, up choices and their side views) or `bulk` (a large
read or a stream: views, tasks, plan, manifest, job.json). A tenant has at most `concurrent` requests of a
kind under way, each counted until the last byte of its response is sent, and starts at most `rate` a second
on average beyond a `burst`. One more is refused at once (TooManyRequests: 429 with Retry-After) rather than
queued: a queue would hold a connection and a session or a thread per waiting request, which is what the
limit is for.

The counts live on the event loop (the dependency is async), so they need no lock; each API process counts its
own requests.
"""

from __future__ import annotations

import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Literal, TypeVar

import anyio
from fastapi import Depends, Request

from services.api.deps import TenantDep
from services.core.domain.errors import TooManyRequests
from services.core.settings import Settings

Kind = Literal["scan", "bulk", "design"]
T = TypeVar("T")
BUSY_RETRY_S = 1  # what a request over a concurrency limit is told to wait: expensive requests take seconds


@dataclass(frozen=True)
class Budget:
    """The limits of one kind of request, per tenant, and the settings that set them (named in refusals)."""

    what: str  # the requests, as a refusal names them
    concurrent: int
    concurrent_setting: str
    rate: float | None = None  # requests started a second, on average; None: no rate limit
    burst: int = 1
    rate_setting: str = ""


def budgets(settings: Settings) -> dict[Kind, Budget]:
    """The budgets of each kind of expensive request, from the settings."""
    return {
        "scan": Budget("requests that read a scan (uploads, registers, up choices, side views)",
                       settings.tenant_scan_concurrency, "OMNIDATA_TENANT_SCAN_CONCURRENCY"),
        "bulk": Budget("bulk reads (views, tasks, plan, manifest, job.json)",
                       settings.tenant_bulk_concurrency, "OMNIDATA_TENANT_BULK_CONCURRENCY",
                       settings.tenant_bulk_rate, settings.tenant_bulk_burst, "OMNIDATA_TENANT_BULK_RATE"),
        "design": Budget("designer plans and previews", settings.tenant_design_concurrency,
                         "OMNIDATA_TENANT_DESIGN_CONCURRENCY"),
    }


class TenantThrottle:
    """Counts each tenant's expensive requests under way and refills each tenant's rate bucket per kind."""

    def __init__(self, limits: dict[Kind, Budget], clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self.clock = clock
        self.under_way: dict[tuple[Kind, str], int] = {}
        self._buckets: dict[tuple[Kind, str], tuple[float, float]] = {}  # (tokens, when last refilled)

    def enter(self, kind: Kind, tenant: str) -> None:
        """Count one more request of `kind` by `tenant`, or raise TooManyRequests saying when to try again."""
        budget = self.limits[kind]
        held = self.under_way.get((kind, tenant), 0)
        if held >= budget.concurrent:
            raise TooManyRequests(
                f"too many {budget.what} at once: {held} under way, at most {budget.concurrent} per tenant "
                f"({budget.concurrent_setting}); wait for one to finish", retry_after_s=BUSY_RETRY_S)
        if budget.rate is not None:
            self._take_token(kind, tenant, budget)
        self.under_way[(kind, tenant)] = held + 1

    def leave(self, kind: Kind, tenant: str) -> None:
        """A request of `kind` by `tenant` has sent its response (or failed)."""
        held = self.under_way.get((kind, tenant), 0) - 1
        if held > 0:
            self.under_way[(kind, tenant)] = held
        else:
            self.under_way.pop((kind, tenant), None)

    def _take_token(self, kind: Kind, tenant: str, budget: Budget) -> None:
        assert budget.rate is not None
        now = self.clock()
        tokens, then = self._buckets.get((kind, tenant), (float(budget.burst), now))
        tokens = min(float(budget.burst), tokens + (now - then) * budget.rate)
        if tokens < 1.0:
            self._buckets[(kind, tenant)] = (tokens, now)
            wait_s = math.ceil((1.0 - tokens) / budget.rate)
            raise TooManyRequests(
                f"too many {budget.what}: at most {budget.rate:g} a second per tenant, {budget.burst} at "
                f"once ({budget.rate_setting}); try again in {wait_s} s", retry_after_s=wait_s)
        self._buckets[(kind, tenant)] = (tokens - 1.0, now)


def _hold(kind: Kind) -> Callable[..., AsyncIterator[None]]:
    async def hold(request: Request, tenant: TenantDep) -> AsyncIterator[None]:
        throttle: TenantThrottle = request.app.state.throttle
        throttle.enter(kind, tenant)
        try:
            yield  # released once the response is sent, a stream's last byte included
        finally:
            throttle.leave(kind, tenant)

    return hold


# route decorators take these in `dependencies=[...]`: they run before the route's session is opened
ScanSlot = Depends(_hold("scan"))
BulkSlot = Depends(_hold("bulk"))
DesignSlot = Depends(_hold("design"))


async def run_bulk(request: Request, work: Callable[[], T]) -> T:
    """`work()` (a bulk read: queries, links, serialization) in one of the few threads all tenants' bulk reads
    share: each is seconds of interpreter time, and the event loop waits its turn for the interpreter behind
    every such thread (four at once held /health for hundreds of milliseconds)."""
    limiter: anyio.CapacityLimiter = request.app.state.bulk_reads.get()
    return await anyio.to_thread.run_sync(work, limiter=limiter)
