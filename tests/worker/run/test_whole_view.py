"""A whole view on the worker that rendered it (issues 20 and 23): after the `passes` task, one statement
claims the rest of the view, pending or queued (every DAG level), the worker derives it all from the pass set
in memory and records everything done in one statement. Postgres and SQLite, real renders of the banana, the
real reaper and heartbeat. Each task keeps its row; outputs are byte-identical to one task at a time and
stored once; a failure inside the batch hands its dependents back; a worker that dies mid-batch has every task
of it re-queued.
"""

from __future__ import annotations

import hashlib
from datetime import timedelta

import pytest
from sqlalchemy import select

from services.core.db.models import Task, utcnow
from services.core.db.states import transition
from services.core.domain.cues import closure
from services.scheduler.reaper import reap_once
from services.worker.run.heartbeat import Heartbeat, expire_leases
from services.worker.run.runner import TaskRunner
from tests.worker.run.test_runner import CUES, banana, counters_match, make_job, queue, runner, sm, task
from tests.worker.run.test_view_batch import outputs

__all__ = ["banana", "sm"]  # fixtures used by name


def view_ids(sm, job_id: int, point: int = 0, view: int = 0) -> dict[str, int]:
    """{cue: task id} of one view's tasks but its render."""
    with sm() as s:
        rows = s.execute(select(Task.cue, Task.id).where(Task.job_id == job_id, Task.point_idx == point,
                                                         Task.view_idx == view, Task.cue != "passes")).all()
    return {str(c): int(i) for c, i in rows}


def test_the_renderer_runs_the_whole_view_in_two_claims_and_the_same_bytes(sm, banana):
    job_id = make_job(sm, banana)
    r = runner(sm, banana, "w1")
    late = queue(sm, job_id, "point_info", 0, 0)  # dispatched (no inputs), its message still in flight
    out = r.run(queue(sm, job_id, "passes", 0, 0))
    view0 = view_ids(sm, job_id)
    assert set(view0) == set(CUES)
    assert out.status == "done" and out.cue == "passes"
    assert sorted(o.cue for o in out.batch) == sorted(CUES)  # every DAG level, pending and queued
    assert [o.status for o in out.batch] == ["done"] * len(CUES)
    order = [o.cue for o in out.batch]
    assert order == [c for c in closure(CUES) if c in CUES]  # inputs before the cues made from them
    # one render; every reader of the pass set ran here, so it was never stored
    assert r.renders == 1 and not banana.store.exists(out.key)
    assert not r.inputs.views  # nothing of the view is left to run: its arrays are freed, not kept in the LRU
    assert (task(sm, out.task_id).size, task(sm, out.task_id).sha256) == (0, None)
    rows = [task(sm, tid) for tid in view0.values()]
    assert {(t.state, t.worker_id, t.attempts) for t in rows} == {("done", "w1", 1)}
    assert len({t.started_at for t in rows}) == 1  # one claim for the rest of the view
    for t in rows:
        data = banana.store.get_bytes(t.output_key)
        assert hashlib.sha256(data).hexdigest() == t.sha256 and len(data) == t.size
    assert {task(sm, tid).state for tid in view_ids(sm, job_id, 0, 1).values()} == {"pending"}  # not view 1
    assert counters_match(sm, job_id)
    # the queued task's message is a no-op, on this worker (a read) and on another (its claim)
    assert r.run(late).status == "skipped" and runner(sm, banana, "w2").run(late).status == "skipped"
    assert task(sm, late).attempts == 1 and counters_match(sm, job_id)

    # the same view one task at a time: the same bytes
    single = make_job(sm, banana)
    one = runner(sm, banana, "w3", worker_batch_views=False)
    assert one.run(queue(sm, single, "passes", 0, 0)).status == "done"
    for cue in closure(CUES):
        if cue in CUES:
            assert one.run(queue(sm, single, cue, 0, 0)).status == "done"
    assert outputs(sm, banana, view_ids(sm, single)) == outputs(sm, banana, view0)

    # a cue of the view made again later (its file lost; resume) renders the view again: the same bytes
    before = outputs(sm, banana, view0)
    with sm() as s:
        transition(s, job_id=job_id, task_ids=[view0["mask_valid"]], from_state="done", to_state="pending")
        s.commit()
    fresh = runner(sm, banana, "w4")
    assert fresh.run(queue(sm, job_id, "mask_valid", 0, 0)).status == "done" and fresh.renders == 1
    assert outputs(sm, banana, view0) == before and counters_match(sm, job_id)


def test_the_pass_set_is_stored_when_a_reader_of_it_runs_elsewhere(sm, banana):
    job_id = make_job(sm, banana)
    other = runner(sm, banana, "w9", worker_batch_views=False)
    assert other.run(queue(sm, job_id, "passes", 0, 1)).status == "done"  # view 1 rendered alone: stored
    mask = queue(sm, job_id, "mask_valid", 0, 1)
    assert other.ledger.claim(mask)  # view 1's mask_valid held by another worker: not part of the batch
    with sm() as s:  # view 1's render runs again (say its first worker's record was lost)
        passes = s.scalar(
            select(Task.id).where(Task.job_id == job_id, Task.cue == "passes", Task.view_idx == 1)
        )
        transition(s, job_id=job_id, task_ids=[passes], from_state="done", to_state="pending")
        s.commit()
    banana.store.delete(task(sm, passes).output_key)
    w1 = runner(sm, banana, "w1")
    out = w1.run(queue(sm, job_id, "passes", 0, 1))
    assert out.status == "done" and mask not in {o.task_id for o in out.batch}
    assert len(w1.inputs.views) == 1  # a task of the view may still come here: its context is kept
    assert banana.store.exists(out.key) and task(sm, passes).size == len(banana.store.get_bytes(out.key))
    assert counters_match(sm, job_id)


def test_a_failure_in_the_batch_hands_its_dependents_back_to_pending(sm, banana, monkeypatch):
    job_id = make_job(sm, banana)
    real_make = TaskRunner.make

    def depth_fails(self, t):
        if t.cue == "depth_zbuffer":
            raise RuntimeError("depth broke")
        return real_make(self, t)

    monkeypatch.setattr(TaskRunner, "make", depth_fails)
    w1 = runner(sm, banana, "w1")
    out = w1.run(queue(sm, job_id, "passes", 0, 0))
    monkeypatch.undo()
    assert len(w1.inputs.views) == 1  # the failed cue's retry may come here: the context is kept
    got = {o.cue: o.status for o in out.all()}
    assert got == {"passes": "done", "point_info": "done", "rgb": "done", "vanishing_points": "done",
                   "depth_zbuffer": "retry", "mask_valid": "skipped"}
    view0 = view_ids(sm, job_id)
    depth, mask = task(sm, view0["depth_zbuffer"]), task(sm, view0["mask_valid"])
    assert (depth.state, depth.attempts, "depth broke" in (depth.error or "")) == ("pending", 1, True)
    assert banana.store.exists(out.key)  # a reader of the pass set is left: it was stored
    # never ran: back as it was before the claim, for the dispatcher to queue once depth_zbuffer is done
    assert (mask.state, mask.attempts, mask.worker_id, mask.lease_until) == ("pending", 0, None, None)
    assert counters_match(sm, job_id)
    with sm() as s:  # the retry backoff is over
        s.execute(Task.__table__.update().where(Task.id == depth.id).values(not_before=None))
        s.commit()
    w2 = runner(sm, banana, "w2")
    retried = w2.run(queue(sm, job_id, "depth_zbuffer", 0, 0))
    assert retried.status == "done" and w2.renders == 0
    # the retry read the stored pass set, so it took the pending dependent with it: no second round for
    # mask_valid
    assert {o.cue: o.status for o in retried.batch} == {"mask_valid": "done"}
    assert (task(sm, mask.id).state, task(sm, mask.id).attempts) == ("done", 1) and counters_match(sm, job_id)


def test_a_stop_that_comes_back_wrapped_from_a_kernel_stops_the_worker_and_fails_nothing(
    sm, banana, monkeypatch
):
    """SIGTERM's SystemExit raised while a numba kernel is being called returns from the call as a SystemError
    caused by it (services.worker.run.stop_signal). Recorded as the task's failure, the stop was lost: the
    worker went on."""
    job_id = make_job(sm, banana)
    real_make = TaskRunner.make

    def stopped_in_a_kernel(self, t):
        if t.cue == "depth_zbuffer":
            try:
                raise SystemExit(143)  # what the worker's SIGTERM handler raised
            except SystemExit as stop:
                raise SystemError(
                    "CPUDispatcher(<function k>) returned a result with an exception set"
                ) from stop
        return real_make(self, t)

    monkeypatch.setattr(TaskRunner, "make", stopped_in_a_kernel)
    passes = queue(sm, job_id, "passes", 0, 0)
    with pytest.raises(SystemExit) as stopped:
        runner(sm, banana, "w1").run(passes)
    monkeypatch.undo()
    assert stopped.value.code == 143
    view0 = {**view_ids(sm, job_id), "passes": passes}
    # nothing recorded: the view stays the stopped worker's until its leases lapse, then it is requeued whole
    assert {(task(sm, t).state, task(sm, t).attempts, task(sm, t).error) for t in view0.values()} == {
        ("running", 1, None)}
    assert counters_match(sm, job_id)


class Died(BaseException):
    """Stands for the worker process dying mid-batch: nothing after it runs (no record, no failure)."""


def test_a_whole_view_whose_worker_dies_is_leased_by_its_beats_then_requeued_task_by_task(
    sm, banana, monkeypatch
):
    job_id = make_job(sm, banana)
    hb = Heartbeat(sm, "dying", lease_s=60)
    hb.extend_after_s = 0.0  # every beat extends the held leases
    dying = TaskRunner(sm, banana.store, runner(sm, banana).settings, "dying", heartbeat=hb,
                       cache_dir=banana.cache_dir, render_threads=1, render_device="cpu", db_retry_s=2.0)
    real_make = TaskRunner.make
    ran: list[str] = []

    def execute_then_die(self, t):
        if len(ran) == 3:  # three outputs made, none stored or recorded: the process is killed here
            expire_leases(sm, ["dying"])
            hb.beat()  # a beat before it dies extends every task of the batch, the pending-claimed ones too
            assert all(task(sm, tid).lease_until > utcnow() for tid in view_ids(sm, job_id).values())
            raise Died()
        ran.append(t.cue)
        return real_make(self, t)

    monkeypatch.setattr(TaskRunner, "make", execute_then_die)
    passes = queue(sm, job_id, "passes", 0, 0)
    with pytest.raises(Died):
        dying.run(passes)
    monkeypatch.undo()
    view0 = {**view_ids(sm, job_id), "passes": passes}
    assert {(task(sm, t).state, task(sm, t).worker_id) for t in view0.values()} == {("running", "dying")}
    assert counters_match(sm, job_id)

    expire_leases(sm, ["dying"])
    with sm() as s:
        res = reap_once(s, queued_timeout_s=3600, now=utcnow() + timedelta(seconds=1))
    assert res.expired_retried >= len(view0)  # the session's Postgres may hold other tests' expired tasks
    assert {task(sm, t).state for t in view0.values()} == {"pending"}
    assert counters_match(sm, job_id)
    with sm() as s:  # the retry backoff is over
        s.execute(Task.__table__.update().where(Task.id.in_(view0.values())).values(not_before=None))
        s.commit()
    out = runner(sm, banana, "w2").run(queue(sm, job_id, "passes", 0, 0))
    assert out.status == "done" and len(out.all()) == len(view0)
    for tid in view0.values():
        row = task(sm, tid)
        assert (row.state, row.worker_id, row.attempts) == ("done", "w2", 2)
        if tid != passes:  # the whole view ran here: its pass set was not stored
            assert hashlib.sha256(banana.store.get_bytes(row.output_key)).hexdigest() == row.sha256
    assert counters_match(sm, job_id)
