"""A store that fills up mid-job, on real parts: a real render (bpy) whose outputs meet a full tmpfs (ENOSPC),
on Postgres and SQLite. The worker hands the view back without counting the attempt or blaming itself, the job
is paused saying "storage full", the scheduler's StoreWatch resumes it once space is back, and the view is
then stored exactly once."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.models import Job, Space, Task, WorkerBlock
from services.core.domain.jobspec import JobSpec
from services.core.ingest.loading import load_space
from services.core.ingest.registry import register_space
from services.core.storage import LocalStore
from services.scheduler.store_watch import StoreWatch
from tests.fixtures.small_disk import fill, small_tmpfs
from tests.worker.run.test_runner import CUES, SPEC, Banana, counters_match, make_job, queue, runner


@pytest.fixture(params=["postgres", "sqlite"])
def sm(request: pytest.FixtureRequest, tmp_path: Path, empty_pg_url: str) -> Iterator[sessionmaker[Session]]:
    """A database of the test's own: a job held for its store there would fail other tests' /ready meanwhile.
    """
    url = empty_pg_url if request.param == "postgres" else f"sqlite:///{tmp_path / 'runner.db'}"
    migrate(url)
    engine = make_engine(url)
    yield make_sessionmaker(engine)
    engine.dispose()


@pytest.fixture()
def banana_on_tmpfs(tmp_path: Path, scenes_dir: Path) -> Iterator[Banana]:
    """The banana registered in a LocalStore on a 24 MiB tmpfs, and its plan."""
    from services.scheduler.planning import make_plan

    with small_tmpfs(tmp_path / "disk", 24) as disk:
        store = LocalStore(disk)
        url = f"sqlite:///{tmp_path / 'registry.db'}"
        migrate(url)
        engine = make_engine(url)
        with Session(engine) as s:
            sp = register_space(s, store, owner="alice", name="banana", source_path=scenes_dir / "ycb_banana")
            s.commit()
            fields = {c.name: getattr(sp, c.name) for c in Space.__table__.columns
                      if c.name not in ("id", "created_at")}
        engine.dispose()
        spec = JobSpec.model_validate({**SPEC, "cues": CUES})
        loaded = load_space(scenes_dir / "ycb_banana", up_axis=spec.up_axis, unit_scale=spec.unit_scale)
        plan = make_plan(loaded, spec, np.random.default_rng([spec.seed, 0]), "banana")
        yield Banana(store, fields, plan, tmp_path / "cache")


def view_tasks(sm, job_id: int) -> list[Task]:
    with sm() as s:
        return list(s.scalars(select(Task).where(Task.job_id == job_id, Task.point_idx == 0,
                                                 Task.view_idx == 0)))


def test_a_full_store_holds_the_job_without_burning_attempts_until_space_returns(sm, banana_on_tmpfs):
    banana = banana_on_tmpfs
    job_id = make_job(sm, banana)
    ballast = fill(banana.store.root)
    r = runner(sm, banana, "w1", max_attempts=1)  # one attempt: a counted one would fail the task for good

    first = r.run(queue(sm, job_id, "passes"))
    assert {o.status for o in first.all()} == {"held"}, [(o.cue, o.status, o.error) for o in first.all()]
    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None and job.state == "paused" and job.paused_by == "storage"
        assert (job.error or "").startswith("storage full: no space left in the object folder")
        # the worker is fine: no failure counted against it, nothing keeps it off the job
        assert s.scalars(select(WorkerBlock).where(WorkerBlock.job_id == job_id)).all() == []
    held = view_tasks(sm, job_id)
    assert {(t.state, t.attempts) for t in held} == {("pending", 0)}
    assert all("storage full" in (t.error or "") for t in held if t.cue == "passes")
    assert counters_match(sm, job_id)
    assert list(banana.store.root.rglob(".*.tmp-*")) == []

    watch = StoreWatch(sm, banana.store, interval_s=0.0)
    assert watch.check() == [] and "storage full" in (watch.last_problem or "")  # still full: stays held
    ballast.unlink()
    assert watch.check() == [job_id]
    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None and job.state == "running" and job.error is None and job.paused_by is None

    again = r.run(queue(sm, job_id, "passes"))
    assert {o.status for o in again.all()} == {"done"}
    done = view_tasks(sm, job_id)
    assert {(t.state, t.attempts) for t in done} == {("done", 1)}
    for t in done:
        if t.cue != "passes":
            assert banana.store.stat(t.output_key).sha256 == t.sha256  # type: ignore[arg-type, union-attr]
    assert counters_match(sm, job_id)
