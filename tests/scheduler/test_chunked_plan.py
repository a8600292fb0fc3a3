"""Plans written in chunks (OMNIDATA_PLAN_CHUNK_VIEWS): the same rows and plan JSON as one chunk, and no
duplicate or stray rows when the planner is killed or the job cancelled between chunks.

Real Postgres (fresh migrated database), a local folder store and real planning of the bunny.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import func, select

from services.core.db.counters import job_progress
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.jobs import cancel_job, create_job
from services.core.db.models import Job, Point, Task, View
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import plan_to_json
from services.core.ingest.registry import register_space
from services.core.settings import get_settings
from services.core.storage import LocalStore
from services.scheduler.loop import Scheduler
from services.scheduler.plan_space import load_for_job
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.transport import NullTransport

SPEC = {
    "cameras": {"mode": "object", "object_count": 12},
    "points": {"count": 300, "min_views": 2, "max_views": 5}, "cues": ["rgb", "normal"],
}
SLOW = {
    "cameras": {"mode": "object", "object_count": 40},
    "points": {"count": 2000, "min_views": 2, "max_views": 40}, "cues": ["rgb"],
}
HEARTBEAT_S = 3


@pytest.fixture()
def env(empty_pg_url: str, tmp_path: Path, scenes_dir: Path) -> Iterator[dict]:
    migrate(empty_pg_url)
    engine = make_engine(empty_pg_url)
    try:
        yield {"sm": make_sessionmaker(engine), "store": LocalStore(tmp_path / "objects"), "tmp": tmp_path,
               "url": empty_pg_url, "bunny": scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"}
    finally:
        engine.dispose()


def scheduler(env: dict, name: str, chunk_views: int, *, processes: bool = False) -> Scheduler:
    settings = get_settings(
        database_url=env["url"], storage_url=f"file://{env['tmp'] / 'objects'}", data_dir=env["tmp"] / "data",
        heartbeat_timeout_s=HEARTBEAT_S, plan_chunk_views=chunk_views,
    )
    return Scheduler(env["sm"], env["store"], NullTransport(), settings, name, plan_in_processes=processes)


def submit(env: dict, spec: dict, owner: str) -> int:
    # the same space name: the same plan (the generator is seeded by job seed and name)
    with env["sm"]() as s:
        space = register_space(s, env["store"], owner=owner, name="bunny", source_path=env["bunny"])
        job = create_job(s, owner=owner, spec=JobSpec.model_validate(spec), spaces=[space])
        s.commit()
        return int(job.id)


def run_until(sched: Scheduler, cond, timeout: float) -> None:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not cond():
        assert time.monotonic() - t0 < timeout, "timed out"
        sched.plan_pending()
        time.sleep(0.05)


def state(env: dict, job_id: int) -> str:
    with env["sm"]() as s:
        return str(s.scalar(select(Job.state).where(Job.id == job_id)))


def task_keys(env: dict, job_id: int) -> list[tuple[int, int, str]]:
    with env["sm"]() as s:
        rows = s.execute(select(Task.point_idx, Task.view_idx, Task.cue).where(Task.job_id == job_id)).all()
    return sorted((int(p), int(v), str(c)) for p, v, c in rows)


def view_rows(env: dict, job_id: int) -> list[tuple]:
    with env["sm"]() as s:
        return sorted(
            tuple(r)
            for r in s.execute(
                select(View.point_idx, View.v, View.camera_idx, View.fov, View.roll).where(
                    View.job_id == job_id
                )
            ).all()
        )


def plan_text(env: dict, job_id: int) -> bytes:
    with env["sm"]() as s:
        job = s.get(Job, job_id)
        assert job is not None and job.plan_summary is not None
        return env["store"].get_bytes(job.plan_summary["spaces"]["bunny"]["plan_key"])


def test_a_plan_in_chunks_is_the_plan_in_one(env: dict) -> None:
    small = submit(env, SPEC, "chunked")
    assert scheduler(env, "s-small", 7).plan_pending() == [small]  # planned inline, 7 views a chunk
    whole = submit(env, SPEC, "whole")
    assert scheduler(env, "s-whole", 10**9).plan_pending() == [whole]
    keys = task_keys(env, small)
    assert keys == task_keys(env, whole) and len(keys) > 7 * 20  # many chunks of 7 views
    assert len(set(keys)) == len(keys)
    assert view_rows(env, small) == view_rows(env, whole)
    # the JSON written piece by piece is plan_to_json of make_plan's whole plan, byte for byte
    spec = JobSpec.model_validate(SPEC)
    plan = make_plan(load_for_job(env["bunny"], spec), spec, space_rng(spec.seed, "bunny"), "bunny")
    assert plan_text(env, small) == plan_text(env, whole) == plan_to_json(plan).encode()
    with env["sm"]() as s:
        assert job_progress(s, small) == job_progress(s, whole)
        assert s.scalar(select(func.count()).select_from(Point).where(Point.job_id == small)) == len(
            plan.points
        )


def test_a_planner_killed_between_chunks_is_retaken_without_duplicate_rows(env: dict) -> None:
    job_id = submit(env, SLOW, "killed")
    dead = scheduler(env, "s-dead", 200, processes=True)
    dead.plan_pending()

    def some_chunks() -> bool:
        with env["sm"]() as s:
            return bool(s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job_id)))

    run_until(dead, some_chunks, 120)
    dead.planners.stop_all()  # type: ignore[union-attr]  # the scheduler dies: its planner with it
    assert state(env, job_id) == "planning"
    other = scheduler(env, "s-other", 200, processes=True)
    run_until(other, lambda: state(env, job_id) != "planning", 240)
    assert state(env, job_id) == "running"
    keys = task_keys(env, job_id)
    assert len(set(keys)) == len(keys)
    with env["sm"]() as s:
        total = s.scalar(select(Job.total_tasks).where(Job.id == job_id))
        assert total == len(keys)
        assert sum(per.get("pending", 0) for per in job_progress(s, job_id).values()) == len(keys)


def test_cancel_between_chunks_leaves_no_pending_task(env: dict) -> None:
    job_id = submit(env, SLOW, "cancelled")
    sched = scheduler(env, "s-1", 200, processes=True)
    sched.plan_pending()

    def some_chunks() -> bool:
        with env["sm"]() as s:
            return bool(s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job_id)))

    run_until(sched, some_chunks, 120)
    with env["sm"]() as s:
        cancel_job(s, s.get(Job, job_id))  # type: ignore[arg-type]
        s.commit()
    sched.plan_pending()
    assert not sched.planners.children  # type: ignore[union-attr]  # stopped within a tick
    with env["sm"]() as s:
        states = dict(
            s.execute(
                select(Task.state, func.count()).where(Task.job_id == job_id).group_by(Task.state)
            ).all()
        )
        assert states == {}, states  # the chunks written before the cancel are removed with their counts
        assert job_progress(s, job_id) == {}
