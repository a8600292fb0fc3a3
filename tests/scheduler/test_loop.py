# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""The scheduler loop end to end: plan with the real planner, dispatch, finish; real Redis; DB restarts."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from kombu import Connection
from sqlalchemy import create_engine, select, text
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.counters import job_progress
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.jobs import create_job
from services.core.db.models import Job, Task
from services.core.domain.jobspec import JobSpec
from services.core.ingest.registry import register_space
from services.core.settings import get_settings
from services.core.storage import LocalStore
from services.scheduler.celery_transport import CeleryTransport
from services.scheduler.loop import Scheduler
from services.scheduler.transport import NullTransport
from tests.conftest import PG_ADMIN_URL, create_pg_database, drop_pg_database
from tests.fixtures.jobs import any_sm, assert_counters_exact, finish, pg_sm, sqlite_sm, task_ids  # noqa: F401  (fixtures)

SPEC = {
    "cues": ["point_info", "rgb"],
    "cameras": {"mode": "object", "object_count": 8},
    "points": {"count": 3, "min_views": 2, "max_views": 2},
}


@pytest.fixture(scope="module")
def own_pg() -> Iterator[str]:
    """A Postgres database of this module's own (its connections get killed on purpose)."""
    url = create_pg_database(prefix="omnidata_loop")
    try:
        migrate(url)
        yield url
    finally:
        drop_pg_database(url)


@pytest.fixture()
def own_sm(own_pg: str) -> Iterator[sessionmaker[Session]]:
    """Committing sessions on the module's database, emptied after each test."""
    engine = make_engine(own_pg)
    try:
        yield make_sessionmaker(engine)
    finally:
        with engine.begin() as c:
            c.execute(text("TRUNCATE job, space RESTART IDENTITY CASCADE"))
        engine.dispose()


def _bunny(scenes_dir: Path) -> Path:
    return scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"


def _submit(sm: sessionmaker[Session], store: LocalStore, scenes_dir: Path, name: str = "bunny",
            **spec_overrides: object) -> int:
    with sm() as s:
        space = register_space(s, store, owner="alice", name=name, source_path=_bunny(scenes_dir))
        job = create_job(
            s, owner="alice", spec=JobSpec.model_validate({**SPEC, **spec_overrides}), spaces=[space]
        )
        s.commit()
        return job.id


def test_embedded_sqlite_job_runs_to_done(sqlite_sm, local_store, scenes_dir, tmp_path):
    settings = get_settings(data_dir=tmp_path, dispatch_window=100)
    job_id = _submit(sqlite_sm, local_store, scenes_dir)
    tr = NullTransport()
    sched = Scheduler(sqlite_sm, local_store, tr, settings, "sched-1")
    res = sched.tick()
    assert res.planned == [job_id]
    with sqlite_sm() as s:
        job = s.get(Job, job_id)
        assert job.state == "running" and job.total_tasks == 6 * 3  # 6 views x (passes, point_info, rgb)
        assert job.plan_summary["spaces"]["bunny"]["views"] == 6
        assert local_store.exists(f"jobs/{job_id}/_plan/bunny.json")
        assert {c for _, c in tr.sent} == {"passes", "point_info"}  # rgb waits for its passes
        for _ in range(5):
            finish(s, job, [i for i, _ in tr.sent])
            tr.sent.clear()
            res = sched.tick()
            if res.finished:
                break
        assert [(f.job_id, f.state) for f in res.finished] == [(job_id, "done")]
        assert_counters_exact(s, job_id)
    lines = local_store.get_bytes(f"jobs/{job_id}/manifest.jsonl").decode().splitlines()
    assert len(lines) == 6 and all(set(json.loads(x)["outputs"]) == {"point_info", "rgb"} for x in lines)
    doc = json.loads(local_store.get_bytes(f"jobs/{job_id}/job.json"))
    assert len(doc["spaces"]["bunny"]["source_to_world"]) == 4
    # how the frame was found, and the predicted surface share (one job.json schema)
    planned = doc["spaces"]["bunny"]
    assert planned["up"]["method"] == "base" and planned["up"]["source_direction"] == [0.0, 1.0, 0.0]
    assert planned["units"]["unit"] == "metres" and planned["valid_fraction"]["views"] == 6


def test_a_space_without_views_fails_the_job_clearly(sqlite_sm, local_store, scenes_dir, tmp_path):
    # no bunny surface point is seen by all 8 cameras around it
    job_id = _submit(
        sqlite_sm, local_store, scenes_dir, points={"count": 3, "min_views": 8, "max_tries_per_point": 5}
    )
    sched = Scheduler(sqlite_sm, local_store, NullTransport(), get_settings(data_dir=tmp_path), "s")
    assert sched.tick().planned == []
    with sqlite_sm() as s:
        job = s.get(Job, job_id)
        assert job.state == "failed"
        assert job.error.startswith("space 'bunny' yields no views: space yields 0 of 3 requested points")
        assert task_ids(s, job_id) == []


def test_postgres_scheduler_puts_messages_on_redis(own_sm, redis_url, tmp_path, scenes_dir):
    store = LocalStore(tmp_path / "objects")
    settings = get_settings(data_dir=tmp_path, broker_url=redis_url, dispatch_window=100)
    job_id = _submit(own_sm, store, scenes_dir)
    transport = CeleryTransport(settings=settings)
    try:
        res = Scheduler(own_sm, store, transport, settings, "sched-pg").tick()
    finally:
        transport.close()
    assert res.planned == [job_id] and res.dispatched.sent == 12
    with own_sm() as s:
        queued = dict(
            s.execute(select(Task.id, Task.cue).where(Task.job_id == job_id, Task.state == "queued")).all()
        )
    got: dict[str, list[int]] = {}
    for queue in (settings.queue_render, settings.queue_derive):
        with Connection(redis_url) as conn:
            with conn.SimpleQueue(queue) as q:
                while True:
                    try:
                        msg = q.get(timeout=0.5)
                    except q.Empty:
                        break
                    assert msg.headers["task"] == "render.cue"
                    args, kwargs, _embed = msg.decode()
                    got.setdefault(queue, []).append(args[0])
                    msg.ack()
    assert sorted(got["render"]) == sorted(i for i, c in queued.items() if c == "passes")
    assert sorted(got["derive"]) == sorted(i for i, c in queued.items() if c == "point_info")


def test_two_schedulers_never_send_a_task_twice(own_sm, tmp_path):
    from tests.fixtures.jobs import make_running_job

    store = LocalStore(tmp_path / "objects")
    with own_sm() as s:
        job = make_running_job(s, store, cues=["point_info", "nonfixated"], n_points=300, views=3)
        total = len(task_ids(s, job.id))
    sent: list[list[tuple[int, str]]] = [[], []]
    start = threading.Barrier(2)

    def run(k: int) -> None:
        tr = NullTransport()
        sched = Scheduler(own_sm, store, tr, get_settings(dispatch_window=10_000), f"s{k}", budget=20)
        start.wait()
        while True:
            sched.dispatch_once()
            with own_sm() as s:
                if not sum(per.get("pending", 0) for per in job_progress(s, job.id).values()):
                    break
        sent[k] = tr.sent

    threads = [threading.Thread(target=run, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    ids = [i for batch in sent for i, _ in batch]
    assert len(ids) == len(set(ids)) == total
    assert sent[0] and sent[1]  # both took part (SKIP LOCKED: they do not queue behind each other)
    with own_sm() as s:
        assert_counters_exact(s, job.id)


def _admin(sql: str, **params: object) -> list[object]:
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            res = c.execute(text(sql), params)
            return list(res.all()) if res.returns_rows else []
    finally:
        admin.dispose()


def _kill_connections(db: str) -> int:
    return len(
        _admin(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = :d AND pid <> "
            "pg_backend_pid()", d=db,
        )
    )


def test_loop_survives_database_outage(own_pg, own_sm, tmp_path, scenes_dir, caplog):
    store = LocalStore(tmp_path / "objects")
    tr = NullTransport()
    sched = Scheduler(own_sm, store, tr, get_settings(data_dir=tmp_path, dispatch_window=100), "sched-x")
    db = own_pg.rsplit("/", 1)[1]
    stop = threading.Event()
    loop = threading.Thread(target=sched.run_forever, args=(stop, 0.1), daemon=True)
    caplog.set_level(logging.INFO, logger="services.scheduler")
    loop.start()
    try:
        first = _submit(own_sm, store, scenes_dir, name="one")
        _wait(
            lambda: {i for i, _ in tr.sent} >= set(_ids(own_sm, first, "passes")) > set(),
            "first job dispatched",
        )
        # Postgres "goes down": no new connections, every open one killed (also mid-query)
        _admin(f'ALTER DATABASE "{db}" ALLOW_CONNECTIONS false')
        try:
            assert _kill_connections(db) >= 1
            _wait(lambda: "scheduler tick failed" in caplog.text, "the loop noticing the outage")
            assert loop.is_alive()
        finally:
            _admin(f'ALTER DATABASE "{db}" ALLOW_CONNECTIONS true')
        second = _submit(own_sm, store, scenes_dir, name="two")
        _wait(
            lambda: {i for i, _ in tr.sent} >= set(_ids(own_sm, second, "passes")) > set(),
            "second job dispatched",
        )
        _wait(lambda: "scheduler recovered" in caplog.text, "the loop recovering")
    finally:
        stop.set()
        loop.join(timeout=30)
    assert not loop.is_alive()


def _ids(sm: sessionmaker[Session], job_id: int, cue: str) -> list[int]:
    with sm() as s:
        return [int(r[0]) for r in s.execute(select(Task.id).where(Task.job_id == job_id, Task.cue == cue))]


def _wait(cond, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for: {what}")


@pytest.mark.slow
def test_cli_once_plans_and_dispatches(own_pg, own_sm, redis_url, tmp_path, scenes_dir, repo_root):
    store = LocalStore(tmp_path / "objects")
    job_id = _submit(own_sm, store, scenes_dir)
    env = {**os.environ, "OMNIDATA_DATABASE_URL": own_pg, "OMNIDATA_BROKER_URL": redis_url,
           "OMNIDATA_STORAGE_URL": store.root.as_uri(), "OMNIDATA_DATA_DIR": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-m", "services.cli", "scheduler", "--once"], cwd=repo_root, env=env,
        capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert f"planned [{job_id}]" in out.stderr and "dispatched 12" in out.stderr
    with own_sm() as s:
        assert s.get(Job, job_id).state == "running"


def test_a_job_cancelled_while_planning_keeps_no_plan(own_sm, tmp_path, scenes_dir, monkeypatch):
    from services.core.db.jobs import cancel_job
    from services.scheduler import chunked_plan

    store = LocalStore(tmp_path / "objects")
    job_id = _submit(own_sm, store, scenes_dir)
    plan_chunks = chunked_plan.plan_chunks

    def plan_then_cancel(*args):
        with own_sm() as other:  # the API cancels while the planner is busy
            cancel_job(other, other.get(Job, job_id))
            other.commit()
        return plan_chunks(*args)

    monkeypatch.setattr(chunked_plan, "plan_chunks", plan_then_cancel)
    sched = Scheduler(own_sm, store, NullTransport(), get_settings(data_dir=tmp_path), "s")
    assert sched.tick().planned == []
    with own_sm() as s:
        assert s.get(Job, job_id).state == "cancelled"
        assert task_ids(s, job_id) == []


def test_planning_errors_are_retried_then_fail_the_job(sqlite_sm, local_store, scenes_dir, tmp_path,
                                                       monkeypatch):
    from sqlalchemy import update

    from services.core.db.models import utcnow
    from services.scheduler import chunked_plan

    job_id = _submit(sqlite_sm, local_store, scenes_dir)
    calls = []

    def flaky(*_args):
        calls.append(1)
        raise RuntimeError("storage hiccup")

    monkeypatch.setattr(chunked_plan, "plan_chunks", flaky)
    sched = Scheduler(sqlite_sm, local_store, NullTransport(), get_settings(data_dir=tmp_path), "s")
    for attempt in (1, 2, 3):
        assert sched.tick().planned == []
        with sqlite_sm() as s:
            job = s.get(Job, job_id)
            assert job.plan_summary["attempts"] == attempt
            if attempt < 3:
                assert job.state == "planning" and job.planner_lease_until > utcnow()  # retried later
                s.execute(update(Job).where(Job.id == job_id).values(planner_lease_until=utcnow()))
                s.commit()
    with sqlite_sm() as s:
        job = s.get(Job, job_id)
        assert job.state == "failed" and "RuntimeError: storage hiccup" in job.error
    assert len(calls) == 3


@pytest.mark.parametrize("views", [{}, {"rgb_source": "photos"}])
def test_running_out_of_the_planning_memory_budget_names_the_cause(sqlite_sm, local_store, scenes_dir,
                                                                   tmp_path, views, monkeypatch):
    from services.scheduler import chunked_plan

    job_id = _submit(sqlite_sm, local_store, scenes_dir, views={**SPEC.get("views", {}), **views})

    def out_of_memory(*_args):
        raise MemoryError

    monkeypatch.setattr(chunked_plan, "plan_chunks", out_of_memory)
    sched = Scheduler(sqlite_sm, local_store, NullTransport(), get_settings(data_dir=tmp_path), "s")
    assert sched.tick().planned == []
    with sqlite_sm() as s:
        job = s.get(Job, job_id)
        assert job.state == "failed" and job.error.startswith("planning ran out of its memory budget of ")
        photos = "downscale the capture's photos, or lower points.count or points.max_views"
        assert job.error.endswith(photos if views else "(OMNIDATA_PLAN_MEMORY_MB): lower points.count or "
                                  "points.max_views"), job.error
