"""Per-tenant limits on expensive requests: the counting and the rate bucket (a fake clock), and the 429 with
Retry-After one tenant gets from the API while another's same requests go through."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.api.throttle import Budget, Kind, TenantThrottle
from services.core.domain.errors import TooManyRequests
from services.core.storage import LocalStore
from tests.fixtures.api import Api, make_api, planned_job


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _throttle(clock: Clock) -> TenantThrottle:
    limits: dict[Kind, Budget] = {
        "scan": Budget("scan reads", 2, "OMNIDATA_TENANT_SCAN_CONCURRENCY"),
        "bulk": Budget("bulk reads", 10, "OMNIDATA_TENANT_BULK_CONCURRENCY", rate=0.5, burst=2,
                       rate_setting="OMNIDATA_TENANT_BULK_RATE"),
    }
    return TenantThrottle(limits, clock)


def test_concurrency_is_counted_per_tenant_and_kind_until_released() -> None:
    throttle = _throttle(Clock())
    throttle.enter("scan", "a")
    throttle.enter("scan", "a")
    with pytest.raises(TooManyRequests, match="2 under way, at most 2 per tenant") as refused:
        throttle.enter("scan", "a")
    assert refused.value.retry_after_s == 1
    throttle.enter("scan", "b")  # another tenant's share is its own
    throttle.enter("bulk", "a")  # and so is another kind's
    throttle.leave("scan", "a")
    throttle.enter("scan", "a")
    for kind, tenant in (("scan", "a"), ("scan", "a"), ("scan", "b"), ("bulk", "a")):
        throttle.leave(kind, tenant)  # type: ignore[arg-type]
    assert throttle.under_way == {}


def test_the_rate_bucket_refills_and_says_when_to_come_back() -> None:
    clock = Clock()
    throttle = _throttle(clock)
    for _ in range(2):  # the burst
        throttle.enter("bulk", "a")
        throttle.leave("bulk", "a")
    with pytest.raises(TooManyRequests, match="at most 0.5 a second per tenant") as refused:
        throttle.enter("bulk", "a")
    assert refused.value.retry_after_s == 2  # one token at 0.5 a second
    throttle.enter("bulk", "b")
    clock.t += 1.0  # half a token: not yet, one second to go
    with pytest.raises(TooManyRequests) as refused:
        throttle.enter("bulk", "a")
    assert refused.value.retry_after_s == 1
    clock.t += 1.0
    throttle.enter("bulk", "a")
    clock.t += 3600  # a long pause refills the burst, no more
    for _ in range(2):
        throttle.enter("bulk", "a")
    with pytest.raises(TooManyRequests):
        throttle.enter("bulk", "a")


@pytest.fixture()
def slow_bulk(pg_url: str, local_store: LocalStore) -> Iterator[Api]:
    with make_api(pg_url, local_store, tenant_bulk_rate=0.2, tenant_bulk_burst=3) as api:
        yield api


def test_a_tenant_over_its_bulk_rate_gets_429_and_another_is_unaffected(slow_bulk: Api, bunny: Path) -> None:
    api = slow_bulk
    mine, theirs = planned_job(api, api.a, bunny), planned_job(api, api.b, bunny)
    views = f"/jobs/{mine}/views?limit=1000&urls=true"
    for path in (views, f"/jobs/{mine}/manifest.jsonl", f"/jobs/{mine}/tasks"):  # the burst, over bulk routes
        assert api.client.get(path, headers=api.a.headers).status_code == 200
    over = api.client.get(views, headers=api.a.headers)
    assert over.status_code == 429
    assert over.headers["retry-after"] == "5"  # one request at 0.2 a second
    detail = over.json()["detail"]
    assert "at most 0.2 a second per tenant" in detail and "OMNIDATA_TENANT_BULK_RATE" in detail
    assert api.client.get(f"/jobs/{mine}", headers=api.a.headers).status_code == 200  # cheap reads go on
    for _ in range(3):  # the other tenant's burst is whole
        r = api.client.get(f"/jobs/{theirs}/views?limit=1000&urls=true", headers=api.b.headers)
        assert r.status_code == 200
