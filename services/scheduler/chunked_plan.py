"""Planning one space of a job chunk by chunk: each chunk's rows committed in a transaction of their own.

Memory stays at one chunk (OMNIDATA_PLAN_CHUNK_VIEWS views) beside the sampled points (planning.stream), and
the plan's JSON goes to a temporary file before the store. Every chunk's transaction ends by re-reading the
job under FOR SHARE: a cancel or a re-take by another scheduler (both update the job row) either waits for
that commit, and then sees its rows (a cancel cancels them, a re-take starts with `clear_plan`), or has
committed first, and then the chunk is rolled back and planning stops (`PlanDropped`). The job stays in
`planning` until its last chunk: the dispatcher, completion and job.json only ever see whole plans.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.models import Job, JobState, Space
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import SpacePlan
from services.core.domain.steering import PlanDistributions
from services.core.ingest.loading import LoadedSpace
from services.core.storage import ObjectStore
from services.scheduler.compile import compile_tasks
from services.scheduler.persist import PlanJsonFile, persist_chunk
from services.scheduler.plan_space import scan_floor_z
from services.scheduler.planning import plan_chunks, space_rng


class PlanDropped(Exception):
    """The job was cancelled or taken over while it was planned: what this planner wrote is not kept."""


@dataclass(frozen=True)
class SpaceWritten:
    """A space planned and persisted: row counts, and the plan's own fields (shortfall, valid fraction...)."""

    cameras: int
    points: int
    views: int
    tasks: int
    whole: SpacePlan
    distributions: dict[str, object] | None = None  # steering.PlanDistributions.record()


@dataclass(frozen=True)
class ChunkTarget:
    """Where a job's chunks go: the database (as the planner holding the job) and the store."""

    sessionmaker: sessionmaker[Session]
    store: ObjectStore
    job_id: int
    planner: str
    chunk_views: int


def still_ours(session: Session, job_id: int, planner: str) -> bool:
    """Whether the job is still planning under `planner`, read under FOR SHARE (Postgres) so that a cancel or
    re-take waits for this transaction's commit."""
    stmt = select(Job.state, Job.planner).where(Job.id == job_id)
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update(read=True)
    row = session.execute(stmt).one_or_none()
    return row is not None and row.state == JobState.PLANNING and row.planner == planner


def plan_and_persist_space(
    target: ChunkTarget, loaded: LoadedSpace, spec: JobSpec, space: Space, cues: list[str], plan_key: str
) -> SpaceWritten:
    """Plan one space of the job in chunks, commit each chunk's rows, then store the plan JSON under
    `plan_key`."""
    chunks = plan_chunks(loaded, spec, space_rng(spec.seed, space.name), space.name, target.chunk_views)
    json_file = PlanJsonFile()
    gathered = PlanDistributions(scan_floor_z(loaded))
    try:
        tasks_written = 0
        for chunk in chunks:
            tasks = compile_tasks(chunk, cues, space.id)
            with target.sessionmaker() as s:
                tasks_written += persist_chunk(s, target.job_id, space.id, chunk, tasks)
                if not still_ours(s, target.job_id, target.planner):
                    s.rollback()
                    raise PlanDropped(f"job {target.job_id} is no longer planning under {target.planner}")
                s.commit()
            json_file.add(chunk)
            gathered.add(chunk)
        assert chunks.whole is not None
        if chunks.views:
            target.store.put_file(plan_key, json_file.finish(chunks.whole), content_type="application/json")
            with target.sessionmaker() as s:  # a delete or cancel after the last chunk missed this object
                state = s.scalar(select(Job.state).where(Job.id == target.job_id))
            if state is None or state == JobState.CANCELLED:  # (a re-taking planner writes the key itself)
                target.store.delete(plan_key)
                raise PlanDropped(f"job {target.job_id} was deleted or cancelled while it was planned")
        return SpaceWritten(chunks.cameras, chunks.points, chunks.views, tasks_written, chunks.whole,
                            gathered.record())
    finally:
        json_file.close()
