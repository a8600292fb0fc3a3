"""Routes that read a stored scan (up choices, side views, uploads) run off the event loop, a few at a time
across tenants, and each tenant has at most its share under way (429 with Retry-After beyond)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.api.spaces import up_choice
from services.core.db.engine import make_engine
from services.core.storage import LocalStore
from tests.fixtures.api import Api, Tenant, live_server, make_api


def _space(api: Api, tenant: Tenant, scan: Path) -> int:
    r = api.client.post("/spaces", files={"file": (scan.name, scan.read_bytes())}, headers=tenant.headers)
    assert r.status_code == 201, r.text
    return int(r.json()["id"])


class GatedReads:
    """Wraps the up choice's scan reader: counts the reads under way (and the most at once) and holds each one
    until `gate` opens; the read itself is the real one, in its limited child process."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.lock = threading.Lock()
        self.now = 0
        self.most = 0
        self.started = 0
        self.real = up_choice.load_space_limited

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        with self.lock:
            self.now += 1
            self.started += 1
            self.most = max(self.most, self.now)
        try:
            assert self.gate.wait(60), "the test never opened the gate"
            return self.real(*args, **kwargs)
        finally:
            with self.lock:
                self.now -= 1


@pytest.fixture()
def one_slot(pg_url: str, local_store: LocalStore) -> Iterator[Api]:
    with make_api(pg_url, local_store, upload_parse_concurrency=1, tenant_scan_concurrency=2) as api:
        yield api


def test_up_choices_share_a_few_slots_and_each_tenant_is_capped(
    one_slot: Api, bunny: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    api = one_slot
    spaces = {api.a.name: _space(api, api.a, bunny), api.b.name: _space(api, api.b, bunny)}
    reads = GatedReads()
    monkeypatch.setattr(up_choice, "load_space_limited", reads)
    answers: list[int] = []
    with live_server(api.app) as base:

        def put(tenant: Tenant) -> None:
            r = httpx.put(f"{base}/spaces/{spaces[tenant.name]}/up", json={}, headers=tenant.headers,
                          timeout=120)
            answers.append(r.status_code)

        callers = [threading.Thread(target=put, args=(t,)) for t in (api.a, api.a, api.b, api.b)]
        for t in callers:
            t.start()
        deadline = time.monotonic() + 30
        while reads.started < 1 or sum(api.app.state.throttle.under_way.values()) < 4:
            assert time.monotonic() < deadline, "the up choices never started"
            time.sleep(0.05)
        time.sleep(0.5)  # time for more reads to start, were they not bounded
        try:
            assert reads.most == 1  # one scan read at a time (OMNIDATA_UPLOAD_PARSE_CONCURRENCY=1), not four
            # the reads are held at the gate: a loop blocked on one would never answer (a timeout, not 200)
            assert httpx.get(f"{base}/health", timeout=10).status_code == 200
            over = httpx.put(f"{base}/spaces/{spaces[api.a.name]}/up", json={}, headers=api.a.headers,
                             timeout=10)
            assert over.status_code == 429 and over.headers["retry-after"] == "1"
            assert "OMNIDATA_TENANT_SCAN_CONCURRENCY" in over.json()["detail"]
            assert "at most 2 per tenant" in over.json()["detail"]
        finally:
            reads.gate.set()
            for t in callers:
                t.join(120)
    assert sorted(answers) == [200, 200, 200, 200]  # both tenants' requests within their share went through
    assert reads.most == 1 and reads.started == 4
    assert api.app.state.throttle.under_way == {}


@pytest.fixture()
def one_connection(pg_url: str, local_store: LocalStore) -> Iterator[tuple[Api, Any]]:
    # a wait for the pool outlasts /health's timeout: a loop blocked on it would never answer /health
    engine = make_engine(pg_url, pool_size=1, max_overflow=0, pool_timeout=60)
    try:
        with make_api(pg_url, local_store, engine=engine) as api:
            yield api, engine
    finally:
        engine.dispose()


def test_health_answers_while_an_up_choice_waits_for_the_database(
    one_connection: tuple[Api, Any], bunny: Path
) -> None:
    api, engine = one_connection
    space = _space(api, api.a, bunny)
    answers: list[int] = []
    with live_server(api.app) as base:
        held = engine.connect()  # the pool's only connection: the up choice waits for it
        try:
            caller = threading.Thread(target=lambda: answers.append(httpx.put(
                f"{base}/spaces/{space}/up", json={}, headers=api.a.headers, timeout=60).status_code))
            caller.start()
            time.sleep(0.5)  # the up choice is waiting for a connection now
            health = httpx.get(f"{base}/health", timeout=10).status_code
            waiting = caller.is_alive() and not answers  # /health answered while the up choice still waited
        finally:
            held.close()
        caller.join(60)
    assert health == 200 and waiting, "/health waited for the database with the up choice"
    assert answers == [200]
