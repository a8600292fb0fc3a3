"""The designer's pool of warm processes, with a stand-in process: one tenant's slow calls leave a process to
the others, a call past the time budget ends its process, and the next call starts a fresh one."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from services.api.designer import pool as pool_module
from services.api.designer.pool import DesignFailed, DesignPool
from services.core.domain.errors import Invalid


@pytest.fixture()
def fake_target(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(pool_module, "TARGET", "tests.api.designer.fake_design:serve")
    yield


def test_a_tenants_slow_calls_leave_a_process_to_another_tenant(fake_target: None) -> None:
    pool = DesignPool(2, timeout_s=30)
    finished: list[str] = []

    def call(name: str, tenant: str, sleep: float) -> None:
        pool.call("sleep", {"sleep": sleep}, tenant=tenant)
        finished.append(name)

    try:
        both = [threading.Thread(target=call, args=(n, n, 0.5)) for n in ("a", "b")]
        for t in both:  # two tenants at once: two processes started, then idle
            t.start()
        for t in both:
            t.join()
        slow = [threading.Thread(target=call, args=(n, "x", 3.0)) for n in ("x1", "x2")]
        for t in slow:
            t.start()
        threading.Event().wait(0.3)
        call("y", "y", 0)  # x holds one process at a time: y gets the other at once
        for t in slow:
            t.join()
    finally:
        pool.close()
    assert finished[2:] == ["y", "x1", "x2"] or finished[2:] == ["y", "x2", "x1"], finished


def test_a_call_past_the_budget_ends_its_process_and_the_next_starts_fresh(fake_target: None) -> None:
    pool = DesignPool(1, timeout_s=2.0)  # a fresh process's first answer under a loaded suite: well within
    try:
        first = pool.call("ping", {})["pid"]
        with pytest.raises(Invalid, match="took longer than 2 s"):
            pool.call("sleep", {"sleep": 30})
        assert not [c for c in pool._children if c.alive()]
        assert pool.call("ping", {})["pid"] != first
    finally:
        pool.close()


def test_a_process_that_dies_is_a_design_failure_and_the_next_call_starts_fresh(fake_target: None) -> None:
    pool = DesignPool(1, timeout_s=30)
    try:
        first = pool.call("ping", {})["pid"]
        with pytest.raises(DesignFailed, match="ended during a crash .exit code 3"):
            pool.call("crash", {"crash": True})
        assert pool.call("ping", {})["pid"] != first
    finally:
        pool.close()


def test_the_first_call_takes_the_warming_process(fake_target: None) -> None:
    pool = DesignPool(2, timeout_s=30)
    try:
        pool.warm()
        pool.warm()  # the page opened twice: one process
        assert len(pool._children) == 1
        warming = pool._children[0].process.pid
        assert pool.call("ping", {}, tenant="x")["pid"] == warming
        assert pool._children[0].owed == 0
    finally:
        pool.close()
