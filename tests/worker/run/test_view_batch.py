"""View batches (issue 20), the derived cue's kind (the whole-view kind, after a render: test_whole_view.py):
a worker taking one of a view's cue tasks claims the view's other queued tasks in one statement, derives them
from the pass set it holds and records them in one statement. Postgres and SQLite, real renders of the banana,
the real reaper. Every task keeps its row and its message; each output is stored and counted exactly once.
"""

from __future__ import annotations

import hashlib
import json
from datetime import timedelta

import pytest
from sqlalchemy import select

from services.core.db.models import Task, utcnow
from services.scheduler.dispatch import dispatch_once
from services.scheduler.reaper import reap_once
from services.scheduler.transport import NullTransport
from services.worker.run.claim import Claimed
from services.worker.run.heartbeat import expire_leases
from services.worker.run.runner import TaskRunner
from tests.worker.run.test_runner import CUES, banana, counters_match, make_job, queue, runner, sm, task

__all__ = ["banana", "sm"]  # fixtures used by name

VIEW_CUES = [c for c in CUES if c != "point_info"]  # point_info is per point: view 0 only


def render(sm, banana, job_id: int, point: int = 0, view: int = 0) -> None:
    """The view's render alone (a worker without view batches), leaving its cues pending."""
    r = runner(sm, banana, "w0", worker_batch_views=False)
    assert r.run(queue(sm, job_id, "passes", point, view)).status == "done"


def queue_view(sm, job_id: int, point: int, view: int) -> dict[str, int]:
    """Queue every task of one view but its render (done first, as the dispatcher would); {cue: task id}."""
    cues = CUES if view == 0 else VIEW_CUES
    return {cue: queue(sm, job_id, cue, point, view) for cue in cues}


def outputs(sm, banana, tids: dict[str, int]) -> dict[str, bytes]:
    """{cue: file bytes}; point_info names its space, which each test job names afresh: read without it."""
    files = {cue: banana.store.get_bytes(task(sm, tid).output_key) for cue, tid in tids.items()}
    if "point_info" in files:
        info = json.loads(files["point_info"])
        assert info.pop("space").startswith("banana-")
        files["point_info"] = json.dumps(info).encode()
    return files


def test_a_view_batch_claims_runs_and_records_the_views_queued_tasks_once(sm, banana):
    job_id = make_job(sm, banana)
    r = runner(sm, banana, "w1")
    render(sm, banana, job_id)
    view0 = queue_view(sm, job_id, 0, 0)
    other_view = queue(sm, job_id, "rgb", 0, 1)  # another view's task: not part of view 0's batch

    first = r.run(view0["rgb"])
    assert first.status == "done" and first.cue == "rgb"
    assert sorted(o.cue for o in first.batch) == sorted(c for c in view0 if c != "rgb")
    assert all(o.status == "done" for o in first.all())
    for cue, tid in view0.items():
        row = task(sm, tid)
        assert (row.state, row.worker_id, row.attempts) == ("done", "w1", 1), cue
        data = banana.store.get_bytes(row.output_key)
        assert hashlib.sha256(data).hexdigest() == row.sha256 and len(data) == row.size
        assert row.duration_s is not None and row.duration_s > 0
    assert task(sm, other_view).state == "queued"
    assert counters_match(sm, job_id)

    # The batched tasks' own messages are no-ops: on this worker (a read, no claim) and on another (the
    # claim).
    assert r.run(view0["depth_zbuffer"]).status == "skipped"
    assert runner(sm, banana, "w2").run(view0["mask_valid"]).status == "skipped"
    assert all(task(sm, tid).attempts == 1 for tid in view0.values())
    assert counters_match(sm, job_id)


def test_batched_outputs_are_byte_identical_to_one_task_at_a_time(sm, banana):
    got = {}
    for batched in (True, False):
        job_id = make_job(sm, banana)
        r = runner(sm, banana, "w1", worker_batch_views=batched)
        render(sm, banana, job_id)
        view0 = queue_view(sm, job_id, 0, 0)
        outcomes = [r.run(tid) for tid in view0.values()]
        assert [o.status for o in outcomes] == (["done"] + ["skipped"] * (len(view0) - 1) if batched
                                                else ["done"] * len(view0))
        assert all(not o.batch for o in outcomes[1:])
        got[batched] = outputs(sm, banana, view0)
        assert counters_match(sm, job_id)
    assert got[True] == got[False]


class Died(BaseException):
    """Stands for the worker process dying mid-batch: nothing after it runs (no record, no failure)."""


def test_a_batch_whose_worker_dies_is_requeued_and_run_once_by_another(sm, banana, monkeypatch):
    job_id = make_job(sm, banana)
    render(sm, banana, job_id)
    view0 = queue_view(sm, job_id, 0, 0)

    dying = runner(sm, banana, "dying")
    real_make = TaskRunner.make
    ran: list[str] = []

    def execute_then_die(self, t):
        if len(ran) == 2:  # two outputs made, none stored or recorded: the process is killed here
            raise Died()
        ran.append(t.cue)
        return real_make(self, t)

    monkeypatch.setattr(TaskRunner, "make", execute_then_die)
    with pytest.raises(Died):
        dying.run(view0["depth_zbuffer"])
    monkeypatch.undo()
    rows = [task(sm, tid) for tid in view0.values()]
    assert {(r.state, r.worker_id) for r in rows} == {("running", "dying")}  # the whole batch was claimed
    assert counters_match(sm, job_id)

    expire_leases(sm, ["dying"])  # what a named worker's successor, or the lease running out, does
    with sm() as s:
        res = reap_once(s, queued_timeout_s=3600, now=utcnow() + timedelta(seconds=1))
    # The Postgres database is the whole session's: other tests' expired tasks may be reaped in the same pass.
    assert res.expired_retried >= len(view0)
    assert all(task(sm, tid).attempts == 1 and task(sm, tid).worker_id is None for tid in view0.values())
    with sm() as s:  # the retry backoff is over
        s.execute(Task.__table__.update().where(Task.id.in_(view0.values())).values(not_before=None))
        s.commit()
    assert {task(sm, tid).state for tid in view0.values()} == {"pending"}
    assert counters_match(sm, job_id)

    requeued = queue_view(sm, job_id, 0, 0)
    assert requeued == view0
    out = runner(sm, banana, "w2").run(view0["mask_valid"])
    assert out.status == "done" and len(out.all()) == len(view0)
    for tid in view0.values():
        row = task(sm, tid)
        assert (row.state, row.worker_id, row.attempts) == ("done", "w2", 2)
        assert hashlib.sha256(banana.store.get_bytes(row.output_key)).hexdigest() == row.sha256
    assert counters_match(sm, job_id)


def test_a_view_batch_counts_once_towards_the_recycle_limit(sm, banana):
    # worker_max_tasks counts messages, as Celery's worker_max_tasks_per_child does: a batch of a view's ~17
    # tasks is one, so a worker is not restarted (imports, space load, first render again) every ~28 views.
    job_id = make_job(sm, banana)
    r = runner(sm, banana, "w1", worker_max_tasks=2)
    render(sm, banana, job_id)
    first = r.run(queue_view(sm, job_id, 0, 0)["rgb"])
    assert len(first.all()) > 2 and all(o.status == "done" for o in first.all())
    assert not first.recycle
    second = r.run(queue(sm, job_id, "rgb", 0, 1))
    assert second.status == "done" and second.recycle


def test_a_pending_task_whose_input_runs_elsewhere_stays_out_of_a_view_batch(sm, banana):
    # Worker A takes a view's point_info message; worker B, running the view's rgb, claims the rest of the
    # view before A's point_info is recorded. vanishing_points (input point_info) must not run in B's batch:
    # A's point_info may still fail, and then vanishing_points fails with it (UpstreamFailed), as the
    # dispatcher's rule says; mask_valid (input depth_zbuffer, in B's batch) runs there.
    job_id = make_job(sm, banana, max_attempts=1)
    render(sm, banana, job_id)
    tids = {cue: queue(sm, job_id, cue) for cue in ("rgb", "depth_zbuffer", "point_info")}
    a = runner(sm, banana, "A")
    held = a.ledger.claim(tids["point_info"])
    assert isinstance(held, Claimed)

    out = runner(sm, banana, "B").run(tids["rgb"])
    ran = {o.cue: o.status for o in out.all()}
    assert ran == dict.fromkeys(("rgb", "depth_zbuffer", "mask_valid"), "done")
    with sm() as s:
        vp = s.scalars(select(Task).where(Task.job_id == job_id, Task.cue == "vanishing_points",
                                          Task.point_idx == 0, Task.view_idx == 0)).one()
    assert (vp.state, vp.worker_id, vp.attempts) == ("pending", None, 0)
    assert counters_match(sm, job_id)

    assert a.ledger.record_failure(held, RuntimeError("boom"), 0.0, max_attempts=1).status == "failed"
    with sm() as s:  # the dispatcher fails what the failed input feeds, and the job can finish
        assert dispatch_once(s, NullTransport(), window=1000).upstream_failed >= 1
    assert task(sm, vp.id).state == "failed" and task(sm, vp.id).error.startswith("UpstreamFailed")
    assert counters_match(sm, job_id)
