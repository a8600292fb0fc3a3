"""What a worker process keeps between tasks: job specs, space rows, plans and rendered views.

A job's tasks arrive one at a time, so re-reading its spec, its space row and its plan JSON for each would
cost a database and a store round trip per task. Views (pass set + memoised intermediates) are kept in a
memory LRU within a byte budget: a job's renders are dispatched ahead of its derived cues, so a worker meets a
view's cues after rendering many other views; each view it dropped meant reading its pass set back and
recomputing its intermediates (3x per view on a room, ~0.1 CPU-s a view).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

from sqlalchemy.orm import Session

from services.core.db.frame_choice import space_frame_for
from services.core.db.jobs import job_root
from services.core.db.models import Job, Space
from services.core.domain.jobspec import JobSpec, SpaceFrame
from services.core.domain.plan import SpacePlan, plan_from_json
from services.core.storage import ObjectStore
from services.worker.context import ViewContext

T = TypeVar("T")

PLAN_CACHE_SIZE = 4  # (job, space) plans kept in memory
# Views kept while they hold more than this fraction of worker_max_memory_mb (and always the last
# VIEW_CACHE_MIN).
VIEW_CACHE_MEMORY_FRACTION = 0.25
VIEW_CACHE_MIN = 4

ViewKey = tuple[int, int, int, int]  # (job, space, point, view)
K = TypeVar("K")


class Measured(Protocol):
    """Anything that says how many bytes it holds (a ViewContext)."""

    def nbytes(self) -> int: ...


Measured_T = TypeVar("Measured_T", bound=Measured)


class DbStep(Protocol):
    """Runs a database step with the worker's retry policy (services.worker.run.claim.TaskLedger.db)."""

    def __call__(self, fn: Callable[[], T], what: str) -> T: ...


@dataclass(frozen=True)
class JobInfo:
    """The parts of a job row a task needs."""

    id: int
    spec: JobSpec
    root: str  # output root, '' for the embedded layout
    component: str
    # space name -> the source_to_world its planner used (job.plan_summary): a re-pick of the space's up
    # while the job renders cannot give its workers a frame other than its planner's
    planned_frames: dict[str, list[list[float]]] = field(default_factory=dict)

    def root_key(self, key: str) -> str:
        """`key` under this job's output root."""
        return f"{self.root}/{key}" if self.root else key

    def frame_for(self, space: Space) -> SpaceFrame:
        """`load_space` keyword arguments of a space: exactly its planner's frame (recorded when it planned);
        for a job planned before that record existed, the frame recomputed from the spec and the space."""
        planned = self.planned_frames.get(space.name)
        return {"source_to_world": planned} if planned is not None else space_frame_for(self.spec, space)


def planned_frames(plan_summary: Mapping[str, object] | None) -> dict[str, list[list[float]]]:
    """Space name -> the source_to_world (4x4) its planner loaded it with, from a job's plan summary."""
    spaces = (plan_summary or {}).get("spaces") or {}
    if not isinstance(spaces, dict):
        return {}
    return {name: rec["source_to_world"] for name, rec in spaces.items()
            if isinstance(rec, dict) and rec.get("source_to_world") is not None}


def trim_lru(views: OrderedDict[K, Measured_T], budget_bytes: int, keep: int = VIEW_CACHE_MIN) -> None:
    """Drop the least recently used entries (first in `views`, each with .nbytes()) while they hold more than
    budget_bytes, keeping at least the `keep` most recent."""
    sizes = [c.nbytes() for c in views.values()]
    total = sum(sizes)
    for size in sizes[:max(0, len(sizes) - keep)]:
        if total <= budget_bytes:
            break
        views.popitem(last=False)
        total -= size


class TaskInputs:
    """Jobs, spaces and plans read once per process; views kept in an LRU of `view_budget_bytes`."""

    def __init__(self, sessionmaker: Callable[[], Session], store: ObjectStore,
                 db: DbStep, view_budget_bytes: int) -> None:
        self.sessionmaker = sessionmaker
        self.store = store
        self.db = db
        self.view_budget_bytes = view_budget_bytes
        self.jobs: dict[int, JobInfo] = {}
        self.spaces: dict[int, Space] = {}
        self.plans: OrderedDict[tuple[int, int], SpacePlan] = OrderedDict()
        self.views: OrderedDict[ViewKey, ViewContext] = OrderedDict()  # contexts holding their pass set

    def job(self, job_id: int) -> JobInfo:
        """The job's spec, output root and component name."""
        info = self.jobs.get(job_id)
        if info is None:
            def load() -> JobInfo:
                with self.sessionmaker() as s:
                    job = s.get(Job, job_id)
                    if job is None:
                        raise LookupError(f"job {job_id} does not exist")
                    spec = JobSpec.model_validate(job.spec)
                    return JobInfo(job.id, spec, job_root(job), job.name or spec.name,
                                   planned_frames(job.plan_summary))

            info = self.db(load, f"load job {job_id}")
            self.jobs[job_id] = info
        return info

    def space(self, space_id: int) -> Space:
        """The space row (detached from its session)."""
        space = self.spaces.get(space_id)
        if space is None:
            def load() -> Space:
                with self.sessionmaker() as s:
                    row = s.get(Space, space_id)
                    if row is None:
                        raise LookupError(f"space {space_id} does not exist")
                    s.expunge(row)
                    return row

            space = self.db(load, f"load space {space_id}")
            self.spaces[space_id] = space
        return space

    def plan(self, job: JobInfo, space: Space) -> SpacePlan:
        """The space's plan in this job, read from the store's `_plan/<space>.json`."""
        k = (job.id, space.id)
        plan = self.plans.get(k)
        if plan is None:
            plan = plan_from_json(self.store.get_bytes(job.root_key(f"_plan/{space.name}.json")))
            self.plans[k] = plan
            while len(self.plans) > PLAN_CACHE_SIZE:
                self.plans.popitem(last=False)
        else:
            self.plans.move_to_end(k)
        return plan

    def cached_view(self, key: ViewKey) -> ViewContext | None:
        """The kept ViewContext of a view (now the most recently used), or None."""
        ctx = self.views.get(key)
        if ctx is not None:
            self.views.move_to_end(key)
        return ctx

    def keep_view(self, key: ViewKey, ctx: ViewContext) -> None:
        """Keep a view's context, dropping the least recently used ones beyond the byte budget."""
        self.views[key] = ctx
        trim_lru(self.views, self.view_budget_bytes)

    def forget_view(self, key: ViewKey) -> None:
        """Drop a view's context (its arrays go back to the allocator for the next view's)."""
        self.views.pop(key, None)

    def max_attempts(self, job_id: int, default: int) -> int:
        """The job's max_attempts when its spec was read, else `default` (the settings')."""
        info = self.jobs.get(job_id)
        return info.spec.max_attempts if info is not None else default
