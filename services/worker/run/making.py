"""A task's bytes from its inputs: the job, the space loaded into the job's world frame (kept between tasks),
the plan, and the view's pass set from this process's memory, the store's pass cache or a render.

The runner (services.worker.run.runner) decides which tasks run together; this module only computes one.
Bytes, not files, come out; all geometry is in the plan (world metres, OpenCV camera axes).
"""

from __future__ import annotations

import functools
import json
import logging
from pathlib import Path

from services.core.db.models import Space
from services.core.domain.cues import OUTPUT_CUES, closure
from services.core.domain.keys import output_key, passes_key
from services.core.domain.plan import PlannedView, SpacePlan
from services.core.ingest.loading import load_space
from services.core.ingest.registry import fetch_space
from services.core.storage import ObjectStore
from services.worker.context import ViewContext
from services.worker.executor import produce, render_passes_for
from services.worker.inputs.caches import JobInfo, TaskInputs
from services.worker.inputs.loaded_cache import read_loaded
from services.worker.inputs.photos import painter_for
from services.worker.inputs.space_cache import SpaceCache, SpaceContext
from services.worker.run.claim import Claimed
from services.worker.run.pass_handoff import PassSets

log = logging.getLogger(__name__)


@functools.cache  # the catalog is fixed: asked of every task, its closure took ~50 us
def needs_passes(cue: str) -> bool:
    """Whether the cue reads the view's pass set (directly or through its inputs)."""
    return "passes" in closure([cue])


class TaskMaker:
    """Computes tasks' files for one worker process; keeps the current space and recent views loaded."""

    def __init__(self, store: ObjectStore, inputs: TaskInputs, cache_dir: Path, *, render_device: str,
                 render_threads: int | None, pass_sets: PassSets, curvature_dir: Path | None = None) -> None:
        self.store = store
        self.pass_sets = pass_sets  # reads back what a renderer handed off
        self.inputs = inputs
        self.cache_dir = cache_dir
        # computed once for this machine's workers (`generate`: the user's, kept across runs)
        self.curvature_dir = curvature_dir if curvature_dir is not None else cache_dir / "curvature"
        self.render_device = render_device
        self.render_threads = render_threads
        self.space_cache = SpaceCache()
        self.renders = 0  # pass sets rendered by this process (one per view, unless a cache was lost)
        self.pass_sets_read = 0  # pass sets read from the store (handed off by a renderer)

    def make(self, t: Claimed) -> tuple[str, bytes]:
        """The task's deterministic key and file bytes (nothing stored)."""
        job = self.inputs.job(t.job_id)
        space = self.inputs.space(t.space_id)
        plan = self.inputs.plan(job, space)
        view = plan.view(t.point, t.view)
        if t.cue == "passes":
            ctx = self._view_context(t, job, space, plan, view)
            key = job.root_key(passes_key(space.name, t.point, t.view))
        else:
            if needs_passes(t.cue):
                ctx = self._view_context(t, job, space, plan, view)
            else:  # plan cues (point_info, nonfixated, vanishing_points) need no render
                ctx = ViewContext(view, job.spec.params, plan=plan)
            key = job.root_key(output_key(t.cue, job.component, space.name, t.point, t.view))
        return key, produce(t.cue, ctx)

    def render_view(self, t: Claimed) -> str:
        """Render the view of a `passes` task into this process's memory (nothing stored); returns its pass
        set's key."""
        job = self.inputs.job(t.job_id)
        space = self.inputs.space(t.space_id)
        plan = self.inputs.plan(job, space)
        self._view_context(t, job, space, plan, plan.view(t.point, t.view))
        return job.root_key(passes_key(space.name, t.point, t.view))

    def close(self) -> None:
        """Free the loaded space and cached views."""
        self.inputs.views.clear()
        self.space_cache.clear()

    def _space_context(self, job: JobInfo, space: Space, plan: SpacePlan | None = None) -> SpaceContext:
        """The space loaded into the world frame of this job (its up_axis/unit_scale), kept between tasks."""
        spec = job.spec
        frame = job.frame_for(space)  # exactly the planner's: a re-pick of the space's up cannot change it
        capture = plan.capture if plan is not None else None
        refined = capture.get("refined") if capture is not None else None  # the planner's colour camera
        photos = f"{spec.uses_photos()}:{json.dumps(refined and refined['correction'], sort_keys=True)}"
        key = f"{space.checksum}:{json.dumps(frame, sort_keys=True)}:photos={photos}"
        device, threads = self.render_device, self.render_threads

        def loader() -> SpaceContext:
            # `omnidata generate` keeps the spaces it loaded in the run's cache folder: no second parse here
            cached = None if spec.uses_photos() else read_loaded(self.cache_dir, space.checksum, frame)
            if cached is not None:
                ctx = SpaceContext.from_loaded(cached, key=key, device=device, threads=threads)
            else:
                path = fetch_space(self.store, space, self.cache_dir)
                loaded = load_space(path, **frame)
                ctx = SpaceContext.from_loaded(loaded, key=key, device=device, threads=threads)
                ctx.photos = painter_for(loaded, spec, refined)
            ctx.curvature_dir = self.curvature_dir
            return ctx

        return self.space_cache.get(key, loader)

    def _view_context(self, t: Claimed, job: JobInfo, space: Space, plan: SpacePlan,
                      view: PlannedView) -> ViewContext:
        """A ViewContext holding the view's pass set: memory LRU, else the store's pass cache, else a
        render."""
        vk = (t.job_id, t.space_id, t.point, t.view)
        ctx = self.inputs.cached_view(vk)
        if ctx is not None:
            return ctx
        params = job.spec.params
        pkey = job.root_key(passes_key(space.name, t.point, t.view))
        passes = None
        if t.cue != "passes":
            try:
                passes = self.pass_sets.read(self.store.get_bytes(pkey))
            except FileNotFoundError:  # the cache was cleared (job finished, then resumed): render again
                log.info("task %d: no cached pass set at %s; rendering the view again", t.id, pkey)
            self.pass_sets_read += passes is not None
        if passes is not None:
            ctx = ViewContext(view, params, passes=passes, plan=plan)
        else:
            space_ctx = self._space_context(job, space, plan)
            ctx = ViewContext(view, params, space=space_ctx, plan=plan, render_passes=self._job_passes(job))
            _ = ctx.passes  # render now, so the time is booked to this task
            self.renders += 1
        self.inputs.keep_view(vk, ctx)
        return ctx

    @staticmethod
    def _job_passes(job: JobInfo) -> frozenset[str]:
        """The render passes the job's cues read: the cached pass set holds those only."""
        return render_passes_for(job.spec.cues if job.spec.cues is not None else OUTPUT_CUES)
