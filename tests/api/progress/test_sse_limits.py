"""Event streams per tenant are capped (429 with a message) and /health answers while the request pool is
full."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import httpx
import pytest

from services.core.storage import LocalStore
from tests.fixtures.api import Api, live_server, make_api


@pytest.fixture()
def capped(pg_url: str, local_store: LocalStore) -> Iterator[Api]:
    with make_api(pg_url, local_store, sse_max_per_tenant=2) as api:
        yield api


def test_a_tenant_over_its_stream_cap_gets_429_and_others_are_unaffected(capped: Api) -> None:
    api = capped
    timeout = httpx.Timeout(10.0)
    with live_server(api.app) as base, contextlib.ExitStack() as streams:
        url_a = f"{base}/events?token={api.a.token}"
        first = streams.enter_context(httpx.stream("GET", url_a, timeout=timeout))
        second = streams.enter_context(httpx.stream("GET", url_a, timeout=timeout))
        assert first.status_code == second.status_code == 200
        over = httpx.get(url_a, timeout=timeout)
        assert over.status_code == 429 and over.headers["retry-after"] == "1"
        assert (
            "at most 2 per tenant" in over.json()["detail"]
            and "OMNIDATA_SSE_MAX_PER_TENANT" in over.json()["detail"]
        )
        with httpx.stream("GET", f"{base}/events?token={api.b.token}", timeout=timeout) as other:
            assert other.status_code == 200  # another tenant's cap is its own
        first.close()  # a closed stream frees its slot once the server notices (its next poll)
        deadline = time.monotonic() + 5
        while True:
            with httpx.stream("GET", url_a, timeout=timeout) as again:
                if again.status_code == 200:
                    break
            assert time.monotonic() < deadline, "the closed stream's slot was never freed"
            time.sleep(0.2)


def test_health_answers_while_every_pool_thread_is_busy(capped: Api) -> None:
    release = threading.Event()
    busy = threading.Semaphore(0)

    # a synchronous route that holds its pool thread, as a slow query or upload write would
    def slow() -> dict:
        busy.release()
        release.wait(30)
        return {}

    capped.app.add_api_route("/test-slow", slow, methods=["GET"])
    pool = 40  # anyio's default thread limiter
    with live_server(capped.app) as base:
        holders = [
            threading.Thread(
                target=httpx.get, args=(f"{base}/test-slow",), kwargs={"timeout": 40}, daemon=True
            )
            for _ in range(pool + 10)
        ]
        for t in holders:
            t.start()
        for _ in range(pool):  # every thread of the pool is now held (the rest of the requests wait for one)
            assert busy.acquire(timeout=30)
        try:
            r = httpx.get(f"{base}/health", timeout=5)  # a pool-bound /health would wait for the release
            assert r.status_code == 200 and r.json()["status"] == "ok"
            assert not release.is_set()
        finally:
            release.set()
            for t in holders:
                t.join(40)


def test_streams_of_a_tenant_share_one_read_per_interval(capped: Api) -> None:
    from services.api.progress.service import Snapshot
    from services.api.progress.shared import SharedPolls

    shared = SharedPolls(capped.app.state.read_sessionmaker, max_age_s=0.5)
    snaps = [Snapshot() for _ in range(20)]
    for snap in snaps:  # 20 streams polling at once: one database read
        shared.poll("tenant-x", None, snap, capped.app.state.rates)
    assert shared.reads == 1
    time.sleep(0.6)
    shared.poll("tenant-x", None, snaps[0], capped.app.state.rates)
    shared.poll("tenant-y", None, Snapshot(), capped.app.state.rates)  # another tenant reads its own jobs
    assert shared.reads == 3
