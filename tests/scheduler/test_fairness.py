# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Dispatch fairness: tenants share each pass evenly, priority counts only within a tenant, the broker queue
is short."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select

from services.core.db.models import Task, Worker, utcnow
from services.scheduler.dispatch import dispatch_once
from services.scheduler.fairness import QUEUED_MIN, QUEUED_PER_WORKER, queued_cap, tenant_turns
from services.scheduler.job_load import JobLoad
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import (  # noqa: F401  (fixtures)
    any_sm,
    assert_counters_exact,
    make_running_job,
    pg_sm,
    sqlite_sm,
)


def _sent_per_job(s, tr: NullTransport, jobs) -> dict[int, int]:
    out = {j.id: 0 for j in jobs}
    for job_id in s.scalars(select(Task.job_id).where(Task.id.in_([i for i, _ in tr.sent]))):
        out[int(job_id)] += 1
    return out


def test_a_small_job_of_another_tenant_gets_half_the_pass_despite_a_big_high_priority_job(
    any_sm, local_store
):
    with any_sm() as s:
        big = make_running_job(
            s, local_store, cues=["point_info"], n_points=300, views=2, owner="alice", priority=9
        )
        small = make_running_job(
            s, local_store, cues=["point_info"], n_points=2, views=2, owner="bob", priority=0
        )
        tr = NullTransport()
        dispatch_once(s, tr, window=2000, budget=10)
        per = _sent_per_job(s, tr, [big, small])
        assert per == {big.id: 5, small.id: 4}  # half the pass each: bob sends his 4 ready tasks at once
        assert_counters_exact(s, small.id)


def test_priority_is_strict_within_a_tenant(any_sm, local_store):
    with any_sm() as s:
        low = make_running_job(
            s, local_store, cues=["point_info"], n_points=20, views=1, owner="alice", priority=0
        )
        high = make_running_job(
            s, local_store, cues=["point_info"], n_points=20, views=1, owner="alice", priority=5
        )
        tr = NullTransport()
        dispatch_once(s, tr, window=2000, budget=8)
        assert _sent_per_job(s, tr, [low, high]) == {low.id: 0, high.id: 8}


def test_tenants_split_evenly_whatever_their_number_of_jobs(any_sm, local_store):
    with any_sm() as s:
        many = [make_running_job(s, local_store, cues=["point_info"], n_points=20, views=1, owner="alice")
                for _ in range(3)]
        one = make_running_job(s, local_store, cues=["point_info"], n_points=20, views=1, owner="bob")
        tr = NullTransport()
        dispatch_once(s, tr, window=2000, budget=12)
        per = _sent_per_job(s, tr, [*many, one])
        assert per[one.id] == 6 and sum(per[j.id] for j in many) == 6


def test_the_queued_cap_bounds_what_waits_in_the_broker(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=30, views=1)
        tr = NullTransport()
        dispatch_once(s, tr, window=2000, queued_cap=5)
        assert len(tr.sent) == 5
        dispatch_once(s, tr, window=2000, queued_cap=5)  # nothing claimed meanwhile: nothing more sent
        assert len(tr.sent) == 5
        assert_counters_exact(s, job.id)


def test_queued_cap_is_sized_by_live_workers(any_sm):
    with any_sm() as s:
        assert queued_cap(s, alive_within_s=30) is None  # no workers known: no cap (embedded runner, tests)
        now = utcnow()
        for k in range(10):
            s.add(Worker(id=f"w{k}", host="h", last_heartbeat=now - timedelta(seconds=1 if k < 6 else 300)))
        s.commit()
        assert queued_cap(s, alive_within_s=30) == max(QUEUED_MIN, 6 * QUEUED_PER_WORKER)


def test_tenant_turns_rotate_tenants_and_keep_priority_order():
    loads = [
        JobLoad(1, 0, {"rgb": {"pending": 1}}, owner="a"), JobLoad(2, 5, {"rgb": {"pending": 1}}, owner="a"),
        JobLoad(3, 0, {"rgb": {"pending": 1}}, owner="b"), JobLoad(4, 0, {"rgb": {"queued": 9}}, owner="c"),
    ]
    first = tenant_turns(loads, window=5, rotation=0)
    assert [[[j.job_id for j in g] for g in t] for t in first] == [[[2], [1]], [[3]]]  # c: nothing pending
    second = tenant_turns(loads, window=5, rotation=1)
    assert [[[j.job_id for j in g] for g in t] for t in second] == [[[3]], [[2], [1]]]
