# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""services.core.db.jobs: creating, claiming, cancelling, retrying and deleting jobs; counters stay exact."""

from __future__ import annotations

import random
import uuid
from collections.abc import Iterator
from datetime import timedelta

import pytest
from sqlalchemy import Engine, delete, func, select, update
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.engine import make_sessionmaker
from services.core.db.jobs import (
    JobStateError,
    cancel_job,
    claim_pending_jobs,
    create_job,
    delete_job,
    pause_job,
    reopen_job,
    resume_job,
    retry_failed,
)
from services.core.db.models import Job, JobSpace, Space, Task, View, utcnow
from services.core.db.states import transition
from services.core.domain.jobspec import JobSpec
from services.scheduler.dispatch import dispatch_once
from services.scheduler.reaper import reap_once
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import (  # noqa: F401  (fixtures)
    any_sm,
    assert_counters_exact,
    claim,
    complete,
    make_running_job,
    make_space,
    pg_sm,
    sqlite_sm,
    states,
    task_counts,
    task_ids,
)


def test_create_job_resolves_cues_per_space(pg_sm):
    with pg_sm() as s:
        plain = make_space(s, name="plain")
        labelled = make_space(s, name="labelled", has_semantics=True)
        job = create_job(s, owner="alice", spec=JobSpec(name="c1"), spaces=[plain, labelled])
        assert job.state == "pending" and job.output_root == f"jobs/{job.id}" and job.name == "c1"
        rows = s.scalars(select(JobSpace).where(JobSpace.job_id == job.id).order_by(JobSpace.position)).all()
        assert [r.space_id for r in rows] == [plain.id, labelled.id]
        assert "segment_semantic" not in rows[0].cues and "segment_semantic" in rows[1].cues
        assert "passes" not in rows[0].cues  # only output cues; the closure is the compiler's business


def test_create_job_refuses_what_a_space_cannot_give(pg_sm):
    with pg_sm() as s:
        plain = make_space(s, name="plain")
        with pytest.raises(ValueError, match=r"space 'plain': cue 'segment_semantic' needs semantic labels"):
            create_job(s, owner="alice", spec=JobSpec(cues=["rgb", "segment_semantic"]), spaces=[plain])
        with pytest.raises(ValueError, match="listed twice"):
            create_job(s, owner="alice", spec=JobSpec(), spaces=[plain, plain])
        with pytest.raises(ValueError, match="does not belong"):
            create_job(s, owner="bob", spec=JobSpec(), spaces=[plain])
        with pytest.raises(ValueError, match="at least one space"):
            create_job(s, owner="alice", spec=JobSpec(), spaces=[])
        assert s.scalar(select(func.count()).select_from(Job)) == 0
        job = create_job(s, owner="alice", spec=JobSpec(cues=["rgb"]), spaces=[plain], output_root="")
        assert job.output_root == ""


@pytest.fixture()
def committed(pg_engine: Engine) -> Iterator[tuple[sessionmaker[Session], str]]:
    """Sessions that really commit (for concurrency), and an owner tag whose rows are deleted afterwards."""
    owner = f"t-{uuid.uuid4().hex[:8]}"
    sm = make_sessionmaker(pg_engine)
    try:
        yield sm, owner
    finally:
        with sm() as s:
            s.execute(delete(Job).where(Job.owner == owner))
            s.execute(delete(Space).where(Space.owner == owner))
            s.commit()


def test_concurrent_claims_never_take_the_same_job(committed):
    sm, owner = committed
    with sm() as s:
        sp = make_space(s, owner=owner)
        ids = {create_job(s, owner=owner, spec=JobSpec(), spaces=[sp]).id for _ in range(4)}
        s.commit()
    # The database is the session's: jobs other tests left claimable may come first in the fair order, so
    # the claims are checked over everything they took, and ours must all be among it.
    with sm() as s1, sm() as s2:
        a = claim_pending_jobs(s1, "planner-a", 2)  # rows stay locked until s1 commits
        b = claim_pending_jobs(s2, "planner-b", 10**6)
        s1.commit()
        s2.commit()
    got_a, got_b = {j.id for j in a}, {j.id for j in b}
    assert len(got_a) == 2 and got_a.isdisjoint(got_b) and ids <= got_a | got_b
    with sm() as s:
        rows = s.execute(select(Job.id, Job.state, Job.planner).where(Job.id.in_(ids))).all()
        assert {r.state for r in rows} == {"planning"}
        assert {r.id for r in rows if r.planner == "planner-a"} == got_a & ids
        # a planner that died: its lease runs out and another scheduler takes the job over
        victim = min(ids)
        s.execute(
            update(Job).where(Job.id == victim).values(planner_lease_until=utcnow() - timedelta(seconds=1))
        )
        s.commit()
        again = {j.id: j.planner for j in claim_pending_jobs(s, "planner-c", 10**6)}
        s.commit()
        assert [i for i in again if i in ids] == [victim] and again[victim] == "planner-c"


def test_claim_on_sqlite(sqlite_sm):
    with sqlite_sm() as s:
        sp = make_space(s)
        job = create_job(s, owner="alice", spec=JobSpec(), spaces=[sp])
        s.commit()
        assert [j.id for j in claim_pending_jobs(s, "me", 5)] == [job.id]
        s.commit()
        assert claim_pending_jobs(s, "other", 5) == []


def test_retry_failed_resets_attempts_and_reopens_the_job(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=2, views=1)
        tr = NullTransport()
        dispatch_once(s, tr, window=10)
        ids = [i for i, _ in tr.sent]
        claim(s, job.id, ids)
        transition(s, job_id=job.id, task_ids=ids, from_state="running", to_state="failed", error="boom")
        job.state = "failed"
        s.commit()
        assert retry_failed(s, job) == 2
        s.commit()
        t = s.scalars(select(Task).where(Task.id == ids[0]).execution_options(populate_existing=True)).one()
        assert (t.state, t.attempts, t.error) == ("pending", 0, None)
        s.refresh(job)
        assert job.state == "running" and job.error is None
        assert_counters_exact(s, job.id)
        cancel_job(s, job)
        s.commit()
        with pytest.raises(JobStateError):
            retry_failed(s, job)
        with pytest.raises(JobStateError):
            cancel_job(s, job)
        with pytest.raises(JobStateError):
            resume_job(s, job)


def test_delete_job_removes_rows_and_only_its_outputs(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=2, views=1)
        other = make_running_job(s, local_store, cues=["rgb"], n_points=1, views=1)
        local_store.put_bytes(f"{job.output_root}/rgb/omnidata/a/x.png", b"1")
        local_store.put_bytes(f"{other.output_root}/rgb/omnidata/a/x.png", b"2")
        assert delete_job(s, local_store, job) >= 2  # the output and the plan JSON
        s.commit()
        assert s.get(Job, job.id) is None
        for model in (Task, View, JobSpace):
            assert s.scalar(select(func.count()).select_from(model).where(model.job_id == job.id)) == 0
        assert not list(local_store.list(f"{job.output_root}/"))
        assert local_store.exists(f"{other.output_root}/rgb/omnidata/a/x.png")
        assert task_ids(s, other.id)


def test_delete_embedded_job_keeps_foreign_files(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=1, views=1, output_root="", name="comp")
        space = s.scalars(select(Space).join(JobSpace).where(JobSpace.job_id == job.id)).one()
        for key in (f"rgb/comp/{space.name}/point_0_view_0_domain_rgb.png", "manifest.jsonl", "job.json",
                    "_cache/passes/x.npz", "notes.txt", "rgb/other/s/y.png"):
            local_store.put_bytes(key, b"x")
        delete_job(s, local_store, job)
        s.commit()
        assert sorted(local_store.list("")) == ["notes.txt", "rgb/other/s/y.png"]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_counters_equal_count_star_after_random_transitions(pg_sm, local_store, seed):
    """Property: whatever sequence of dispatches, claims, completions, failures, reaps and retries happens,
    the incremental counters equal COUNT(*) by cue and state."""
    rng = random.Random(seed)
    with pg_sm() as s:
        job = make_running_job(
            s, local_store, cues=["reshading", "edge_texture", "nonfixated"], n_points=4, views=3
        )

        def pick(state: str) -> list[int]:
            ids = task_ids(s, job.id, state=state)
            return rng.sample(ids, rng.randint(1, len(ids))) if ids else []

        ops = ["dispatch", "claim", "done", "fail", "retry_later", "reap", "retry_failed", "pause", "resume",
               "lease_lost"]
        weights = [4, 4, 4, 1, 1, 1, 1, 1, 2, 1]
        seen: set[str] = set()
        for _ in range(80):
            op = rng.choices(ops, weights)[0]
            if op == "dispatch":
                dispatch_once(s, NullTransport(), window=rng.randint(1, 40), budget=rng.randint(1, 30),
                              rotation=rng.randint(0, 3), thorough=rng.random() < 0.2)
            elif op == "claim":
                claim(s, job.id, pick("queued"))
            elif op == "done":
                complete(s, job, pick("running"))
            elif op == "fail":
                transition(
                    s, job_id=job.id, task_ids=pick("running"), from_state="running", to_state="failed",
                    error="x",
                )
            elif op == "retry_later":
                transition(
                    s, job_id=job.id, task_ids=pick("running"), from_state="running", to_state="pending",
                    not_before=utcnow() + timedelta(seconds=rng.choice([-5, 5])),
                )
            elif op == "lease_lost":
                s.execute(update(Task).where(Task.id.in_(pick("running")))
                          .values(lease_until=utcnow() - timedelta(seconds=1)))
            elif op == "reap":
                reap_once(s, queued_timeout_s=rng.choice([0, 300]))
            elif op == "retry_failed" and job.state in ("running", "paused", "failed", "done"):
                retry_failed(s, job)
            elif op == "pause" and job.state == "running":
                pause_job(s, job)
            elif op == "resume" and job.state == "paused":
                resume_job(s, job)
            s.commit()
            assert_counters_exact(s, job.id)
            seen.update(st for per_cue in task_counts(s, job.id).values() for st in per_cue)
        assert {"pending", "queued", "running", "done"} <= seen  # the walk really moved tasks around
        cancel_job(s, job)
        s.commit()
        assert_counters_exact(s, job.id)
        assert not {"pending", "queued"} & set(states(s, task_ids(s, job.id)).values())


def test_reopen_job_requeues_inflight_tasks_without_counting_the_attempt(any_sm, local_store):
    """The embedded resume path is a core operation: it must run on Postgres as well as on SQLite."""
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=1)
        tr = NullTransport()
        dispatch_once(s, tr, window=10)
        ids = [i for i, _ in tr.sent]
        claim(s, job.id, ids[:2])  # two running (attempt 1), one still queued
        s.commit()
        done = reopen_job(s, local_store, job)
        s.commit()
        assert done.requeued == 3
        rows = s.execute(select(Task.state, Task.attempts, Task.worker_id).where(Task.id.in_(ids))
                         .execution_options(populate_existing=True)).all()
        assert {tuple(r) for r in rows} == {("pending", 0, None)}
        assert_counters_exact(s, job.id)
