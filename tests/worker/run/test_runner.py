"""TaskRunner against the execution contract, on Postgres and SQLite, with a real plan of the banana scan,
real renders (bpy) and a real local object store.

Each test builds a running job from one plan made once per module (services.scheduler.planning.make_plan)
and queues tasks the way the dispatcher does (pending -> queued), then runs them through the runner.
"""

from __future__ import annotations

import hashlib
import io
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import Engine, select
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.counters import job_progress
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.jobs import create_job, root_key
from services.core.db.models import Job, Space, Task, Worker, WorkerBlock, utcnow
from services.core.db.states import transition
from services.core.domain.jobspec import JobSpec
from services.core.domain.keys import output_key, passes_key
from services.core.domain.plan import SpacePlan
from services.core.ingest.loading import load_space
from services.core.ingest.registry import register_space
from services.core.settings import get_settings
from services.core.storage import LocalStore, ObjectInfo
from services.scheduler.compile import compile_tasks
from services.scheduler.persist import persist_space
from services.scheduler.reaper import reap_once
from services.worker.inputs.caches import trim_lru
from services.worker.run.claim import Outcome, format_error
from services.worker.run.heartbeat import Heartbeat
from services.worker.run.runner import TaskRunner

SPEC = {
    "cameras": {"mode": "object", "object_count": 6},
    "points": {"count": 1, "min_views": 2, "max_views": 2},
    "views": {"resolution": 32},
}
CUES = ["point_info", "rgb", "depth_zbuffer", "mask_valid", "vanishing_points"]


@dataclass
class Banana:
    """The banana registered once in a module-wide store, and a plan of it made once."""

    store: LocalStore
    space_fields: dict[str, Any]
    plan: SpacePlan
    cache_dir: Path


@pytest.fixture(scope="module")
def banana(tmp_path_factory: pytest.TempPathFactory, scenes_dir: Path) -> Banana:
    from services.scheduler.planning import make_plan

    root = tmp_path_factory.mktemp("runner")
    store = LocalStore(root / "objects")
    url = f"sqlite:///{root / 'registry.db'}"
    migrate(url)
    engine = make_engine(url)
    with Session(engine) as s:
        sp = register_space(s, store, owner="alice", name="banana", source_path=scenes_dir / "ycb_banana")
        s.commit()
        fields = {
            c.name: getattr(sp, c.name) for c in Space.__table__.columns if c.name not in ("id", "created_at")
        }
    engine.dispose()
    spec = JobSpec.model_validate({**SPEC, "cues": CUES})
    loaded = load_space(scenes_dir / "ycb_banana", up_axis=spec.up_axis, unit_scale=spec.unit_scale)
    plan = make_plan(loaded, spec, np.random.default_rng([spec.seed, 0]), "banana")
    assert len(plan.views) == 2
    return Banana(store, fields, plan, root / "cache")


@pytest.fixture(params=["postgres", "sqlite"])
def sm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    """A session factory on a database whose commits are real (Postgres: the session DB; SQLite: a new
    file)."""
    if request.param == "postgres":
        engine: Engine = request.getfixturevalue("pg_engine")
        yield make_sessionmaker(engine)
        return
    url = f"sqlite:///{tmp_path / 'runner.db'}"
    migrate(url)
    engine = make_engine(url)
    yield make_sessionmaker(engine)
    engine.dispose()


def make_job(sm: sessionmaker[Session], banana: Banana, **spec_over: Any) -> int:
    """A running job over the banana's plan with every task pending; returns its id."""
    spec = JobSpec.model_validate({**SPEC, "cues": CUES, **spec_over})
    with sm() as s:
        sp = Space(**{**banana.space_fields, "name": f"banana-{uuid.uuid4().hex[:6]}"})
        s.add(sp)
        s.flush()
        job = create_job(s, owner="alice", spec=spec, spaces=[sp], output_root=f"jobs/{uuid.uuid4().hex}")
        plan = SpacePlan(sp.name, banana.plan.cameras, banana.plan.points, banana.plan.views)
        tasks = compile_tasks(plan, CUES, sp.id)
        n = persist_space(s, banana.store, job, sp.id, plan, tasks).tasks
        job.state, job.total_tasks = "running", n
        s.commit()
        return job.id


def queue(sm: sessionmaker[Session], job_id: int, cue: str, point: int = 0, view: int = 0) -> int:
    """Mark one task queued (as the dispatcher does) and return its id."""
    with sm() as s:
        tid = s.scalar(select(Task.id).where(Task.job_id == job_id, Task.cue == cue, Task.point_idx == point,
                                             Task.view_idx == view))
        assert tid is not None
        assert transition(s, job_id=job_id, task_ids=[tid], from_state="pending", to_state="queued",
                          queued_at=utcnow())
        s.commit()
        return int(tid)


def task(sm: sessionmaker[Session], tid: int) -> Task:
    with sm() as s:
        row = s.get(Task, tid)
        assert row is not None
        return row


def runner(
    sm: sessionmaker[Session], banana: Banana, worker: str = "w1", store: Any = None, **settings: Any
) -> TaskRunner:
    return TaskRunner(sm, store or banana.store, get_settings(lease_s=60, **settings), worker,
                      cache_dir=banana.cache_dir, render_threads=1, render_device="cpu", db_retry_s=2.0)


def counters_match(sm: sessionmaker[Session], job_id: int) -> bool:
    from sqlalchemy import func

    with sm() as s:
        truth: dict[str, dict[str, int]] = {}
        for cue, state, n in s.execute(select(Task.cue, Task.state, func.count()).where(Task.job_id == job_id)
                                       .group_by(Task.cue, Task.state)):
            truth.setdefault(cue, {})[state] = int(n)
        return job_progress(s, job_id) == truth


# ------------------------------------------------------------------------------------------ claim and done


def test_plan_cue_runs_once_and_records_size_and_sha(sm, banana):
    job_id = make_job(sm, banana)
    tid = queue(sm, job_id, "point_info", 0, 1)
    out = runner(sm, banana).run(tid)
    assert out.status == "done" and out.cue == "point_info" and out.labels == 1
    row = task(sm, tid)
    with sm() as s:
        job = s.get(Job, job_id)
        space_name = s.get(Space, row.space_id).name
        expect_key = root_key(job, output_key("point_info", job.name, space_name, 0, 1))
    assert (row.state, row.worker_id, row.attempts, row.output_key) == ("done", "w1", 1, expect_key)
    data = banana.store.get_bytes(expect_key)
    assert row.size == len(data) and row.sha256 == hashlib.sha256(data).hexdigest()
    assert row.duration_s is not None and row.duration_s > 0 and row.lease_until is None
    assert b'"world_to_camera"' in data and b'"K"' in data
    assert counters_match(sm, job_id)


def test_duplicate_delivery_leaves_one_output_and_one_done_row(sm, banana):
    job_id = make_job(sm, banana)
    tid = queue(sm, job_id, "vanishing_points")
    # vanishing_points waits for point_info in the DAG; the runner itself only needs the plan
    first, second = runner(sm, banana, "w1").run(tid), runner(sm, banana, "w2").run(tid)
    assert first.status == "done"
    assert second.status == "skipped" and "not queued" in (second.error or "")
    row = task(sm, tid)
    assert (row.state, row.worker_id, row.attempts) == ("done", "w1", 1)
    with sm() as s:
        assert (
            s.scalar(
                select(Task.id).where(
                    Task.job_id == job_id, Task.cue == "vanishing_points", Task.point_idx == 0,
                    Task.view_idx == 0, Task.state == "done",
                )
            )
            == tid
        )
    assert len([k for k in banana.store.list(row.output_key.rsplit("/", 1)[0] + "/")
                if k.endswith("point_0_view_0_domain_vanishing_points.json")]) == 1
    assert counters_match(sm, job_id)


@pytest.mark.bpy
def test_render_once_then_derive_from_the_pass_cache(sm, banana):
    job_id = make_job(sm, banana)
    r = runner(sm, banana, worker_batch_views=False)  # one task a message: the render alone, then each cue
    p = r.run(queue(sm, job_id, "passes", 0, 0))
    assert p.status == "done" and p.labels == 0  # the pass set is internal, not a label
    with sm() as s:
        job = s.get(Job, job_id)
        sp = s.get(Space, task(sm, p.task_id).space_id)
        pkey = root_key(job, passes_key(sp.name, 0, 0))
    assert p.key == pkey and banana.store.exists(pkey)
    assert r.renders == 1
    rgb = r.run(queue(sm, job_id, "rgb", 0, 0))
    mask = r.run(queue(sm, job_id, "mask_valid", 0, 0))
    assert (rgb.status, mask.status) == ("done", "done")
    assert r.renders == 1  # derived from the cached pass set, no second render
    # A fresh worker (no memory cache) reads the pass set from the store: same bytes as the first.
    other = runner(sm, banana, "w2", worker_batch_views=False)
    depth = other.run(queue(sm, job_id, "depth_zbuffer", 0, 0))
    assert depth.status == "done" and other.renders == 0
    img = np.asarray(Image.open(io.BytesIO(banana.store.get_bytes(rgb.key))))
    m = np.asarray(Image.open(io.BytesIO(banana.store.get_bytes(mask.key))))
    assert img.shape == (32, 32, 3) and m.shape == (32, 32)
    assert 0 < (m == 255).sum() < m.size  # the banana is in view, with background around it
    assert counters_match(sm, job_id)


class CacheHintStore:
    """The local store, recording each put_many's keys and whether it asked to keep the files cached."""

    def __init__(self, inner: LocalStore) -> None:
        self.inner, self.puts = inner, []

    def put_many(self, items: list[tuple[str, bytes]], *, keep_cached: bool = True) -> list[ObjectInfo]:
        self.puts.append(([key for key, _ in items], keep_cached))
        return self.inner.put_many(items, keep_cached=keep_cached)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_a_pass_set_stays_in_the_page_cache_and_cue_files_leave_it(sm, banana):
    """The pass set is read again (by the view's tasks on other workers); a cue's file is not."""
    job_id = make_job(sm, banana)
    store = CacheHintStore(banana.store)
    r = runner(sm, banana, store=store, worker_batch_views=False)
    assert r.run(queue(sm, job_id, "passes", 0, 0)).status == "done"
    assert r.run(queue(sm, job_id, "rgb", 0, 0)).status == "done"
    (passes, passes_kept), (rgb, rgb_kept) = store.puts
    assert passes[0].endswith(".npz") and passes_kept
    assert rgb[0].endswith("_domain_rgb.png") and not rgb_kept


@dataclass
class Sized:
    size: int

    def nbytes(self) -> int:
        return self.size


def test_view_cache_keeps_views_within_its_byte_budget_least_recently_used_out():
    from collections import OrderedDict

    views = OrderedDict((k, Sized(100)) for k in "abcdefgh")
    trim_lru(views, budget_bytes=1000, keep=2)
    assert list(views) == list("abcdefgh")  # 800 bytes: all kept (more than the old fixed 4 views)
    views["i"], views["j"], views["k"] = Sized(100), Sized(100), Sized(350)
    trim_lru(views, budget_bytes=1000, keep=2)
    assert list(views) == list("efghijk")  # oldest out until <= 1000 bytes
    trim_lru(views, budget_bytes=10, keep=2)
    assert list(views) == ["j", "k"]  # the most recent ones stay even over budget


def test_view_context_nbytes_counts_its_pass_set_and_memoised_arrays():
    from services.worker.context import ViewContext
    from services.worker.passes import ViewGeometry, ViewPasses

    n = 8
    passes = ViewPasses(geometry=ViewGeometry(np.eye(4), 1.0, n), depth_z=np.ones((n, n), np.float32),
                        normal_world=None, rgb=np.zeros((n, n, 3), np.uint8), face_index=None)
    ctx = ViewContext(None, passes=passes)
    assert ctx.nbytes() == n * n * 4 + n * n * 3
    ctx.memo("pair", lambda: (np.zeros(10, np.float64), np.zeros(5, np.uint8)))
    ctx.memo("file", lambda: b"12345")
    assert ctx.nbytes() == n * n * 7 + 80 + 5 + 5


# ------------------------------------------------------------------------------------------ failures


def test_failure_retries_with_backoff_then_fails_for_good_with_the_error(sm, banana):
    job_id = make_job(sm, banana, max_attempts=2)
    with sm() as s:
        job = s.get(Job, job_id)
        sp_name = s.get(Space, s.scalar(select(Task.space_id).where(Task.job_id == job_id).limit(1))).name
        banana.store.delete(root_key(job, f"_plan/{sp_name}.json"))  # the worker cannot load the plan
    tid = queue(sm, job_id, "point_info")
    before = utcnow()
    first = runner(sm, banana).run(tid)
    assert first.status == "retry" and "ObjectNotFoundError" in (first.error or "")
    row = task(sm, tid)
    assert row.state == "pending" and row.attempts == 1 and row.worker_id is None
    assert row.not_before is not None and row.not_before >= before + timedelta(seconds=4)  # backoff(1) = 5 s
    # type, message, traceback tail
    assert "ObjectNotFoundError" in (row.error or "") and "  at " in row.error
    with sm() as s:  # the dispatcher would wait for not_before; the test moves it on at once
        transition(
            s, job_id=job_id, task_ids=[tid], from_state="pending", to_state="queued", queued_at=utcnow()
        )
        s.commit()
    second = runner(sm, banana, "w2").run(tid)
    assert second.status == "failed"
    row = task(sm, tid)
    assert row.state == "failed" and row.attempts == 2 and row.finished_at is not None
    assert row.error.startswith("ObjectNotFoundError: ")
    assert counters_match(sm, job_id)


def test_worker_failing_three_times_is_blocked_and_hands_tasks_back(sm, banana):
    job_id = make_job(sm, banana, max_attempts=5)
    with sm() as s:
        job = s.get(Job, job_id)
        sp_name = s.get(Space, s.scalar(select(Task.space_id).where(Task.job_id == job_id).limit(1))).name
        banana.store.delete(root_key(job, f"_plan/{sp_name}.json"))
    r = runner(sm, banana, "bad-worker", worker_batch_views=False)  # one failure per message (no view batch)
    tids = [queue(sm, job_id, "point_info", 0, v) for v in (0, 1)] + [
        queue(sm, job_id, "vanishing_points", 0, 0)
    ]
    assert [r.run(t).status for t in tids] == ["retry", "retry", "retry"]
    with sm() as s:
        block = s.get(WorkerBlock, ("bad-worker", job_id))
        assert block is not None and block.failures == 3
        assert block.until is not None and block.until > utcnow() + timedelta(minutes=9)
    handed = queue(sm, job_id, "vanishing_points", 0, 1)
    out = r.run(handed)
    assert out.status == "blocked"
    row = task(sm, handed)
    assert row.state == "pending" and row.attempts == 0 and row.worker_id is None  # attempts unchanged
    # another worker is not blocked: it claims the same task
    assert runner(sm, banana, "good-worker").run(queue_again(sm, job_id, handed)).status == "retry"
    assert counters_match(sm, job_id)


def queue_again(sm: sessionmaker[Session], job_id: int, tid: int) -> int:
    with sm() as s:
        assert transition(s, job_id=job_id, task_ids=[tid], from_state="pending", to_state="queued",
                          queued_at=utcnow())
        s.commit()
    return tid


# ------------------------------------------------------------------------------------------ job state


def test_paused_job_task_is_handed_back_and_cancelled_job_task_is_ignored(sm, banana):
    job_id = make_job(sm, banana)
    tid = queue(sm, job_id, "point_info")
    with sm() as s:
        s.get(Job, job_id).state = "paused"
        s.commit()
    out = runner(sm, banana).run(tid)
    assert out.status == "paused"
    row = task(sm, tid)
    assert row.state == "pending" and row.attempts == 0 and row.queued_at is None
    with sm() as s:
        job = s.get(Job, job_id)
        job.state = "running"
        s.commit()
    tid = queue_again(sm, job_id, tid)
    with sm() as s:
        from services.core.db.jobs import cancel_job

        cancel_job(s, s.get(Job, job_id))
        s.commit()
    out = runner(sm, banana).run(tid)
    assert out.status == "skipped" and task(sm, tid).state == "cancelled"
    assert counters_match(sm, job_id)


class StallingStore:
    """A store whose put of one key first lets the lease run out and another worker finish the task."""

    def __init__(self, inner: LocalStore, on_put: Any) -> None:
        self.inner, self.on_put, self.fired = inner, on_put, False

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectInfo:
        if not self.fired:
            self.fired = True
            self.on_put()
        return self.inner.put_bytes(key, data, content_type)

    def put_many(self, items: list[tuple[str, bytes]], *, keep_cached: bool = True) -> list[ObjectInfo]:
        if not self.fired:
            self.fired = True
            self.on_put()
        return self.inner.put_many(items, keep_cached=keep_cached)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_completion_of_a_reaped_task_is_discarded(sm, banana):
    job_id = make_job(sm, banana)
    tid = queue(sm, job_id, "point_info", 0, 1)

    def lease_runs_out() -> None:
        with sm() as s:  # the real reaper, an hour later: the slow worker's lease has expired
            assert reap_once(s, queued_timeout_s=3600, now=utcnow() + timedelta(hours=1)).expired_retried >= 1
        with sm() as s:
            s.execute(Task.__table__.update().where(Task.id == tid).values(not_before=None))
            s.commit()
        queue_again(sm, job_id, tid)
        assert runner(sm, banana, "fast").run(tid).status == "done"

    slow = runner(sm, banana, "slow", store=StallingStore(banana.store, lease_runs_out))
    out = slow.run(tid)
    assert out.status == "discarded"
    row = task(sm, tid)
    assert (row.state, row.worker_id, row.attempts) == ("done", "fast", 2)
    data = banana.store.get_bytes(row.output_key)  # both wrote identical bytes; the row is single
    assert hashlib.sha256(data).hexdigest() == row.sha256
    assert counters_match(sm, job_id)


def test_unknown_task_and_recycle_after_max_tasks(sm, banana):
    job_id = make_job(sm, banana)
    r = runner(sm, banana, worker_max_tasks=1)
    assert r.run(10**9).status == "skipped"
    out = r.run(queue(sm, job_id, "point_info"))
    assert out.status == "done" and out.recycle


# ------------------------------------------------------------------------------------------ heartbeat


def test_heartbeat_upserts_the_worker_and_extends_only_its_own_lease(sm, banana):
    job_id = make_job(sm, banana)
    mine, theirs = queue(sm, job_id, "point_info", 0, 0), queue(sm, job_id, "point_info", 0, 1)
    past = utcnow() - timedelta(seconds=30)
    with sm() as s:
        transition(s, job_id=job_id, task_ids=[mine], from_state="queued", to_state="running", worker_id="hb",
                   lease_until=past)
        transition(
            s, job_id=job_id, task_ids=[theirs], from_state="queued", to_state="running", worker_id="other",
            lease_until=past,
        )
        s.commit()
    hb = Heartbeat(sm, "hb", queues=["render", "derive"], lease_s=120)
    hb.set_current(mine)
    hb.record_done("rgb", 1)
    hb.beat()
    with sm() as s:
        w = s.get(Worker, "hb")
        assert w is not None and w.queues == ["render", "derive"] and w.current_task_id == mine
        assert w.tasks_done == 1 and w.labels == {"rgb": 1} and w.labels_per_s > 0
        first_beat, started = w.last_heartbeat, w.started_at
        # just claimed (with a full lease): the task row is left alone until a third of the lease has passed
        assert s.get(Task, mine).lease_until == past
    hb.extend_after_s = 0.0  # as if 40 s had passed
    hb.beat()
    with sm() as s:
        w = s.get(Worker, "hb")
        assert w.last_heartbeat > first_beat and w.started_at == started  # the upsert keeps the start time
        assert s.get(Task, mine).lease_until > utcnow() + timedelta(seconds=100)
        assert s.get(Task, theirs).lease_until < utcnow()
    hb.set_current(None)
    hb.beat()
    with sm() as s:
        assert s.get(Worker, "hb").current_task_id is None
    hb.register()  # a new run of the worker: only then does the row's start move
    with sm() as s:
        assert s.get(Worker, "hb").started_at > started


def test_heartbeat_start_writes_the_worker_row_before_it_returns(sm):
    # The row must exist before the runner's first claim, so the first beat is the caller's, not the thread's.
    beats_by: list[str] = []

    def spy() -> Session:
        beats_by.append(threading.current_thread().name)
        return sm()

    hb = Heartbeat(spy, "hb-start", lease_s=120, interval_s=3600).start()
    try:
        assert beats_by == [threading.current_thread().name]
        with sm() as s:
            assert s.get(Worker, "hb-start") is not None
    finally:
        hb.stop(timeout=1.0)


def test_format_error_keeps_type_message_and_traceback_tail():
    def inner() -> None:
        raise ValueError("bad pixel")

    try:
        inner()
    except ValueError as e:
        text = format_error(e)
    assert text.splitlines()[0] == "ValueError: bad pixel"
    assert "in inner" in text.splitlines()[-1]
    assert Outcome(1, "done", cue="passes").labels == 0 and Outcome(1, "done", cue="rgb").labels == 1
