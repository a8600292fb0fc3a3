# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Dispatch: the cue DAG, the per-job window, priorities, fairness, cancel and pause (Postgres and SQLite)."""

from __future__ import annotations

from collections import Counter
from datetime import timedelta

import pytest
from sqlalchemy import select, update

from services.core.db.jobs import cancel_job, pause_job, resume_job
from services.core.db.models import Task, utcnow
from services.core.domain.cues import CATALOG
from services.scheduler.dispatch import dispatch_once, ready_tasks
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import (  # noqa: F401  (fixtures)
    any_sm,
    assert_counters_exact,
    claim,
    complete,
    finish,
    make_running_job,
    pg_sm,
    sqlite_sm,
    states,
    task_ids,
)


def _cues_of(session, ids):
    return dict(session.execute(select(Task.id, Task.cue).where(Task.id.in_(ids))).all())


def test_dag_is_respected_until_the_job_is_all_done(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(
            s, local_store, cues=["edge_texture", "reshading", "vanishing_points", "nonfixated"], n_points=2,
            views=2,
        )
        sent_cues: list[set[str]] = []
        done: set[tuple[int, int, str]] = set()
        for _ in range(10):
            tr = NullTransport()
            res = dispatch_once(s, tr, window=1000)
            if not tr.sent:
                break
            assert res.sent == len(tr.sent)
            rows = s.execute(
                select(Task.id, Task.point_idx, Task.view_idx, Task.cue).where(
                    Task.id.in_([i for i, _ in tr.sent])
                )
            ).all()
            for _tid, p, v, cue in rows:  # every input of a dispatched task is already done
                for inp in CATALOG[cue].inputs:
                    assert (p, 0 if CATALOG[inp].per_point else v, inp) in done, (cue, inp)
            assert {c for _, c in tr.sent} == {r.cue for r in rows}
            sent_cues.append({c for _, c in tr.sent})
            finish(s, job, [i for i, _ in tr.sent])
            done.update((p, v, c) for _t, p, v, c in rows)
            assert_counters_exact(s, job.id)
        # wave 1: no inputs; wave 2: render cues + plan-derived; wave 3: edge_texture needs rgb
        assert sent_cues[0] == {"passes", "point_info", "nonfixated"}
        assert sent_cues[1] == {"rgb", "normal", "depth_zbuffer", "vanishing_points"}
        assert sent_cues[2] == {"edge_texture", "reshading"}
        assert len(sent_cues) == 3
        assert set(states(s, task_ids(s, job.id)).values()) == {"done"}


def test_window_bounds_queued_plus_running(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=10, views=2)  # 20 tasks
        tr = NullTransport()
        assert dispatch_once(s, tr, window=5).sent == 5
        assert dispatch_once(s, tr, window=5).sent == 0  # full window
        first = [i for i, _ in tr.sent]
        claim(s, job.id, first[:3])
        s.commit()
        assert dispatch_once(s, tr, window=5).sent == 0  # running tasks count against the window too
        complete(s, job, first[:3])
        assert dispatch_once(s, tr, window=5).sent == 3
        assert len(set(tr.sent)) == 8  # never the same task twice
        assert_counters_exact(s, job.id)


def test_higher_priority_job_goes_first(pg_sm, local_store):
    with pg_sm() as s:
        low = make_running_job(s, local_store, cues=["point_info"], n_points=10, views=2, priority=0)
        high = make_running_job(s, local_store, cues=["point_info"], n_points=8, views=2, priority=5)
        tr = NullTransport()
        res = dispatch_once(s, tr, window=1000, budget=10)
        assert res.per_job == {high.id: 10}
        # high has 16 ready tasks: 6 left, then low gets the rest of the budget
        res = dispatch_once(s, tr, window=1000, budget=10)
        assert res.per_job == {high.id: 6, low.id: 4}
        assert list(res.per_job) == [high.id, low.id]


def test_equal_priority_jobs_share_round_robin(pg_sm, local_store):
    with pg_sm() as s:
        a = make_running_job(s, local_store, cues=["point_info"], n_points=10, views=2)
        b = make_running_job(s, local_store, cues=["point_info"], n_points=10, views=2)
        res = dispatch_once(s, NullTransport(), window=1000, budget=10)
        assert res.per_job == {a.id: 5, b.id: 5}
        res = dispatch_once(s, NullTransport(), window=1000, budget=3, rotation=1)
        assert res.per_job == {b.id: 2, a.id: 1}  # the rotation decides who gets the odd one
        # one task per pass: the rotation alternates which job is served
        first = [next(iter(dispatch_once(s, NullTransport(), window=1000, budget=1, rotation=r).per_job))
                 for r in range(4)]
        assert Counter(first) == {a.id: 2, b.id: 2}
        # a job with fewer ready tasks than its share leaves the rest to the other
        c = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1)
        res = dispatch_once(s, NullTransport(), window=1000, budget=12, rotation=2)
        assert res.sent == 12 and res.per_job[c.id] == 1


def test_cancel_stops_dispatch_at_once(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=3, views=2)
        tr = NullTransport()
        dispatch_once(s, tr, window=2)
        queued = [i for i, _ in tr.sent]
        n = cancel_job(s, job)
        s.commit()
        assert n == len(task_ids(s, job.id))  # nothing was running: every task cancelled
        assert set(states(s, queued).values()) == {"cancelled"}
        assert dispatch_once(s, tr, window=100).sent == 0
        assert_counters_exact(s, job.id)


def test_pause_and_resume(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=2)
        pause_job(s, job)
        s.commit()
        assert dispatch_once(s, NullTransport(), window=100).sent == 0
        resume_job(s, job)
        s.commit()
        assert dispatch_once(s, NullTransport(), window=100).sent == 4


def test_backoff_delays_a_retried_task(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1)
        ids = task_ids(s, job.id)
        s.execute(update(Task).where(Task.id == ids[0]).values(not_before=utcnow() + timedelta(minutes=5)))
        s.commit()
        assert [i for i, _ in ready_tasks(s, job.id, 10)[0]] == ids[1:]
        assert [i for i, _ in ready_tasks(s, job.id, 10, now=utcnow() + timedelta(minutes=6))[0]] == ids


class _Broken:
    def send(self, batch):
        raise ConnectionError("broker down")


def test_failed_send_puts_tasks_back_to_pending(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=1)
        res = dispatch_once(s, _Broken(), window=100)
        assert res.sent == 0 and res.requeued == 2
        assert set(states(s, task_ids(s, job.id)).values()) == {"pending"}
        assert_counters_exact(s, job.id)
        assert dispatch_once(s, NullTransport(), window=100).sent == 2


@pytest.mark.parametrize("n_jobs", [3])
def test_only_running_jobs_are_served(pg_sm, local_store, n_jobs):
    with pg_sm() as s:
        jobs = [
            make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1) for _ in range(n_jobs)
        ]
        jobs[0].state = "paused"
        jobs[1].state = "done"
        s.commit()
        assert dispatch_once(s, NullTransport(), window=100).per_job == {jobs[2].id: 1}


class _FailsAfterFirst:
    def __init__(self):
        self.sent: list[tuple[int, str]] = []

    def send(self, batch):
        if self.sent:
            raise ConnectionError("broker went away")
        self.sent.extend(batch)


def test_a_send_failure_midway_puts_back_only_the_unsent(pg_sm, local_store, monkeypatch):
    import services.scheduler.dispatch as dispatch

    monkeypatch.setattr(dispatch, "SEND_CHUNK", 2)
    with pg_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=2)
        tr = _FailsAfterFirst()
        res = dispatch_once(s, tr, window=100)
        assert (res.sent, res.requeued) == (2, 4)
        st = states(s, task_ids(s, job.id))
        assert sorted(st[i] for i, _ in tr.sent) == ["queued", "queued"]
        assert sorted(st.values()).count("pending") == 4
        assert_counters_exact(s, job.id)


def test_tasks_whose_input_failed_fail_too_and_the_job_finishes(any_sm, local_store):
    from services.core.db.states import transition
    from services.scheduler.completion import complete_once

    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["edge_texture"], n_points=1, views=2)
        tr = NullTransport()
        dispatch_once(s, tr, window=100)
        passes = sorted(i for i, _ in tr.sent)  # passes of views 0 and 1
        claim(s, job.id, passes)
        transition(s, job_id=job.id, task_ids=passes[:1], from_state="running", to_state="failed",
                   error="RenderError: Cycles crashed")
        complete(s, job, passes[1:])
        for _ in range(4):  # view 0: rgb fails upstream, then edge_texture; view 1 runs through
            tr = NullTransport()
            dispatch_once(s, tr, window=100)
            finish(s, job, [i for i, _ in tr.sent])
        rows = s.execute(
            select(Task.view_idx, Task.cue, Task.state, Task.error).where(Task.job_id == job.id)
        ).all()
        by = {(v, c): (st, err) for v, c, st, err in rows}
        assert by[(0, "rgb")][0] == by[(0, "edge_texture")][0] == "failed"
        assert by[(0, "rgb")][1].startswith("UpstreamFailed")
        assert by[(1, "rgb")][0] == by[(1, "edge_texture")][0] == "done"
        assert_counters_exact(s, job.id)
        (fin,) = complete_once(s, local_store)
        assert fin.state == "failed" and "RenderError: Cycles crashed" in fin.error
        assert fin.error.startswith("3 of 6 tasks failed")


def test_scans_use_the_pending_only_index_under_a_generic_plan(pg_sm, local_store):
    """The dispatch index holds pending tasks only (migration 0004); the scan names the predicate's literal,
    so even a generic plan (a prepared statement after a few executions) can use it, and finished tasks have
    no entry in
    it."""
    from sqlalchemy import text
    from sqlalchemy.dialects import postgresql

    from services.scheduler.dispatch import PENDING_LITERAL

    with pg_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=4, views=2)
        definition = s.scalar(
            text("SELECT indexdef FROM pg_indexes WHERE indexname = 'ix_task_pending_job_id_cue_id'")
        )
        assert definition is not None and "WHERE" in definition and "'pending'" in definition
        scan = (
            select(Task.id)
            .where(Task.job_id == job.id, Task.state == PENDING_LITERAL, Task.cue == "point_info")
            .order_by(Task.id)
            .limit(5)
        )
        sql = str(scan.compile(dialect=postgresql.dialect()))
        s.execute(text("SET LOCAL plan_cache_mode = force_generic_plan"))
        s.execute(text("SET LOCAL enable_seqscan = off"))
        prepared = sql.replace("%(job_id_1)s", "$1").replace("%(cue_1)s", "$2").replace("%(param_1)s", "$3")
        s.execute(text(f"PREPARE pending_scan (bigint, text, int) AS {prepared}"))
        plan = "\n".join(
            r[0] for r in s.execute(text(f"EXPLAIN EXECUTE pending_scan ({job.id}, 'point_info', 5)"))
        )
        assert "ix_task_pending_job_id_cue_id" in plan, plan
        s.execute(text("DEALLOCATE pending_scan"))
        s.rollback()
        tr = NullTransport()
        dispatch_once(s, tr, window=100)
        finish(s, job, [i for i, _ in tr.sent])
        left = s.scalar(
            text("SELECT count(*) FROM task WHERE job_id = :j AND state = 'pending'"), {"j": job.id}
        )
        assert left == 0 and s.scalar(text("SELECT count(*) FROM task WHERE job_id = :j"), {"j": job.id}) == 8
        assert_counters_exact(s, job.id)
