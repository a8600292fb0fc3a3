# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Reaper: expired leases go back to pending (or fail when out of attempts); lost queued tasks are re-sent."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select, update

from services.core.db.jobs import cancel_job
from services.core.db.models import Task, Worker, utcnow
from services.scheduler.dispatch import dispatch_once
from services.scheduler.reaper import reap_once
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import (  # noqa: F401  (fixtures)
    any_sm,
    assert_counters_exact,
    claim,
    make_running_job,
    pg_sm,
    sqlite_sm,
    states,
    task_ids,
)


def _running(s, job, n, lease_s):
    tr = NullTransport()
    dispatch_once(s, tr, window=n)
    ids = [i for i, _ in tr.sent]
    claim(s, job.id, ids, worker="w-dead", lease_s=lease_s)
    s.commit()
    return ids


def test_expired_lease_goes_back_to_pending_with_backoff(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=4, views=1)
        dead = _running(s, job, 2, lease_s=-1)  # a worker that stopped heart-beating
        s.execute(update(Task).where(Task.id == dead[1]).values(lease_until=utcnow() + timedelta(minutes=5)))
        s.commit()
        now = utcnow()
        res = reap_once(s, queued_timeout_s=300, now=now)
        assert (res.expired_retried, res.expired_failed, res.lost_requeued) == (1, 0, 0)
        t = s.scalars(select(Task).where(Task.id == dead[0]).execution_options(populate_existing=True)).one()
        assert t.state == "pending" and t.worker_id is None and t.lease_until is None
        assert t.attempts == 1  # the lost attempt counts
        assert t.not_before is not None and t.not_before > now
        assert states(s, [dead[1]]) == {dead[1]: "running"}  # its lease is still valid
        assert_counters_exact(s, job.id)


def test_expired_lease_out_of_attempts_fails_with_reason(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1, max_attempts=2)
        (tid,) = _running(s, job, 1, lease_s=-1)
        s.execute(update(Task).where(Task.id == tid).values(attempts=2))
        s.commit()
        res = reap_once(s, queued_timeout_s=300)
        assert res.expired_failed == 1 and res.expired_retried == 0
        t = s.scalars(select(Task).where(Task.id == tid).execution_options(populate_existing=True)).one()
        assert t.state == "failed"
        assert "LeaseExpired" in t.error and "w-dead" in t.error and "max_attempts=2" in t.error
        assert_counters_exact(s, job.id)


def test_lost_queued_tasks_are_requeued_and_sent_again(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=1)
        tr = NullTransport()
        dispatch_once(s, tr, window=100)
        ids = [i for i, _ in tr.sent]
        assert reap_once(s, queued_timeout_s=300).lost_requeued == 0  # fresh: left alone
        res = reap_once(s, queued_timeout_s=300, now=utcnow() + timedelta(seconds=301))
        assert res.lost_requeued == 3
        t = s.scalars(select(Task).where(Task.id == ids[0]).execution_options(populate_existing=True)).one()
        assert t.state == "pending" and t.queued_at is None and t.attempts == 0
        again = NullTransport()
        dispatch_once(s, again, window=100)
        assert sorted(again.sent) == sorted(tr.sent)
        assert_counters_exact(s, job.id)


def test_cancelled_jobs_dead_tasks_are_cancelled(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=1)
        dead = _running(s, job, 1, lease_s=-1)
        cancel_job(s, job)
        s.commit()
        assert states(s, dead) == {dead[0]: "running"}  # cancel leaves running tasks alone
        assert reap_once(s, queued_timeout_s=300).expired_cancelled == 1
        assert set(states(s, task_ids(s, job.id)).values()) == {"cancelled"}
        assert_counters_exact(s, job.id)


def _worker(s, worker_id, beat_age_s):
    s.add(Worker(id=worker_id, host="h", last_heartbeat=utcnow() - timedelta(seconds=beat_age_s)))
    s.commit()


def test_dead_workers_tasks_are_requeued_before_their_lease_runs_out(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=4, views=1)
        tr = NullTransport()
        dispatch_once(s, tr, window=4)
        ids = [i for i, _ in tr.sent]
        started = utcnow() - timedelta(seconds=60)
        for k, (worker, beat_age_s) in enumerate([("w-dead", 45), ("w-alive", 2), ("w-no-row", None)]):
            claim(s, job.id, [ids[k]], worker=worker, lease_s=300)
            s.execute(update(Task).where(Task.id == ids[k]).values(started_at=started))
            if beat_age_s is not None:
                _worker(s, worker, beat_age_s)
        # a task claimed after its worker's last beat: that worker was alive then
        claim(s, job.id, [ids[3]], worker="w-dead", lease_s=300)
        s.commit()

        assert reap_once(s, queued_timeout_s=300).total == 0  # without a heartbeat timeout: leases only
        res = reap_once(s, queued_timeout_s=300, dead_after_s=30)
        # w-no-row: every runner beats before its first claim, so it died before that beat landed
        assert (res.expired_retried, res.dead_worker, res.expired_failed) == (2, 2, 0)
        assert states(s, ids) == {ids[0]: "pending", ids[1]: "running", ids[2]: "pending", ids[3]: "running"}
        for tid, worker in ((ids[0], "w-dead"), (ids[2], "w-no-row")):
            t = s.scalars(select(Task).where(Task.id == tid).execution_options(populate_existing=True)).one()
            assert t.worker_id is None and t.attempts == 1 and "WorkerDead" in t.error and worker in t.error
        assert_counters_exact(s, job.id)

        # the task claimed after its worker's last beat is lost when its lease runs out
        res = reap_once(s, queued_timeout_s=3600, dead_after_s=30, now=utcnow() + timedelta(seconds=301))
        assert res.expired_retried == 2 and res.dead_worker == 0
