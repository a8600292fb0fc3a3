# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Re-sending queued tasks whose message a dead worker may hold, or that sit queued while workers idle."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select, update

from services.core.db.models import Task, Worker, utcnow
from services.core.settings import get_settings
from services.scheduler.dispatch import dispatch_once
from services.scheduler.resend import IdleWatch, resend_stuck
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import (  # noqa: F401  (fixtures)
    any_sm,
    assert_counters_exact,
    claim,
    make_running_job,
    pg_sm,
    sqlite_sm,
    states,
)

DEAD_AFTER_S = 30.0


def _queued(s, job, n, age_s):
    """Dispatch n tasks and age their queued_at by `age_s` seconds."""
    tr = NullTransport()
    dispatch_once(s, tr, window=1000, budget=n)
    ids = [i for i, _ in tr.sent]
    s.execute(update(Task).where(Task.id.in_(ids)).values(queued_at=utcnow() - timedelta(seconds=age_s)))
    s.commit()
    return ids


def _worker(s, worker_id, beat_age_s, *, current=None, done=0, queues=("render", "derive"), run_age_s=None):
    row = s.get(Worker, worker_id)
    if row is None:
        row = Worker(id=worker_id, host="h", queues=list(queues), started_at=utcnow() - timedelta(hours=1))
        s.add(row)
    if run_age_s is not None:  # a new run of the worker began then
        row.started_at = utcnow() - timedelta(seconds=run_age_s)
    row.last_heartbeat = utcnow() - timedelta(seconds=beat_age_s)
    row.current_task_id = current
    row.tasks_done = done
    s.commit()


def _pass(s, watch, tr=None, **kw):
    tr = tr or NullTransport()
    res = resend_stuck(
        s, tr, get_settings(), watch, dead_after_s=DEAD_AFTER_S, stuck_after_s=DEAD_AFTER_S, **kw
    )
    return res, tr


def test_tasks_queued_before_a_worker_died_are_sent_again_once(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=1)
        before = _queued(s, job, 2, age_s=60)  # queued while the worker lived; it may hold their messages
        _worker(s, "w-dead", beat_age_s=40)  # declared dead 10 s ago
        after = _queued(s, job, 3, age_s=0)  # dispatched after it was declared dead: not its messages
        watch = IdleWatch()
        res, tr = _pass(s, watch)
        assert sorted(i for i, _ in tr.sent) == sorted(before) and res.after_death == 2
        assert set(states(s, before + after).values()) == {"queued"}  # no state change: only a new message
        assert_counters_exact(s, job.id)
        res, tr = _pass(s, watch)  # the same death sends nothing twice
        assert tr.sent == [] and res.total == 0


def test_a_worker_restarted_under_its_name_counts_as_its_previous_run_dying(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=1)
        before = _queued(s, job, 2, age_s=60)  # queued while the previous run lived: it may hold them
        watch = IdleWatch()
        _worker(s, "w", beat_age_s=2, current=before[0], done=3)
        res, tr = _pass(s, watch)
        assert tr.sent == [] and res.total == 0  # alive and busy
        # killed and restarted in place within the heartbeat timeout: never silent long enough to be declared
        # dead; its new run's row says when it began
        _worker(s, "w", beat_age_s=0, current=None, done=3, run_age_s=1)
        after = _queued(s, job, 1, age_s=0)
        res, tr = _pass(s, watch)
        assert sorted(i for i, _ in tr.sent) == sorted(before) and res.after_death == 2
        assert states(s, after) == {after[0]: "queued"}
        _worker(s, "w", beat_age_s=0, current=after[0], done=3)  # later beats of the same run
        res, tr = _pass(s, watch)
        assert tr.sent == [] and res.total == 0


def test_a_live_busy_worker_causes_no_resend(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=1)
        ids = _queued(s, job, 2, age_s=120)
        watch = IdleWatch()
        _worker(s, "w-busy", beat_age_s=3, current=ids[0], done=5)
        _pass(s, watch)
        _worker(s, "w-busy", beat_age_s=0, current=None, done=6)  # between two tasks at its beat: not idle
        res, tr = _pass(s, watch)
        assert tr.sent == [] and res.total == 0


def test_old_queued_tasks_are_sent_again_when_a_consumer_sat_idle(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=1)
        old = _queued(s, job, 2, age_s=DEAD_AFTER_S + 5)
        young = _queued(s, job, 1, age_s=1)  # may still be on its way: left alone
        watch = IdleWatch()
        _worker(s, "w-idle", beat_age_s=4, done=7)
        res, tr = _pass(s, watch)
        assert tr.sent == []  # one observation is not enough to call a worker idle
        _worker(s, "w-idle", beat_age_s=0, done=7)
        res, tr = _pass(s, watch)
        assert sorted(i for i, _ in tr.sent) == sorted(old) and res.idle_consumers == 2
        assert states(s, young) == {young[0]: "queued"}


def test_an_idle_worker_of_another_queue_does_not_count(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=1)  # a derive-queue cue
        _queued(s, job, 2, age_s=DEAD_AFTER_S + 5)
        watch = IdleWatch()
        for age in (4, 0):
            _worker(s, "w-render", beat_age_s=age, queues=("render",))
            res, tr = _pass(s, watch)
        assert tr.sent == []


def test_a_claimed_task_is_not_sent_again_and_a_duplicate_claim_is_refused(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=1)
        ids = _queued(s, job, 2, age_s=60)
        claim(s, job.id, ids[:1], worker="w-live")
        s.commit()
        _worker(s, "w-dead", beat_age_s=40)
        res, tr = _pass(s, IdleWatch())
        assert [i for i, _ in tr.sent] == ids[1:]
        assert claim(s, job.id, ids[:1], worker="w-other") == []  # the second delivery finds it running
        s.rollback()
        assert s.scalar(select(Task.worker_id).where(Task.id == ids[0])) == "w-live"


def test_a_failed_send_keeps_the_tasks_queued(any_sm, local_store):
    class Broken:
        def send(self, batch):
            raise ConnectionError("redis down")

    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1)
        ids = _queued(s, job, 1, age_s=60)
        _worker(s, "w-dead", beat_age_s=40)
        res, _ = _pass(s, IdleWatch(), tr=Broken())
        assert res.send_failed and states(s, ids) == {ids[0]: "queued"}
