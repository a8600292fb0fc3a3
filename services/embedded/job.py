"""The embedded job of `omnidata generate`: SQLite and a local folder under --out, the same job reused to
resume, and the scheduler's loop driving W local worker processes until the job is final.

Resuming (in-flight tasks back to pending, missing outputs made again) and requeueing on Ctrl-C are the
service's own operations (services.core.db.jobs.reopen_job / requeue_inflight).
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import sys
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from services.core import gpu_devices
from services.core.db.jobs import cancel_job, create_job, job_spaces, reopen_job, requeue_inflight
from services.core.db.manifest import write_job_files
from services.core.db.models import JOB_TERMINAL_STATES, Job, JobState, Space
from services.core.domain.errors import Conflict, Invalid
from services.core.domain.jobspec import JobSpec
from services.core.domain.keys import JOB_JSON_KEY, MANIFEST_KEY
from services.core.ingest.loading import LoadedSpace
from services.core.ingest.registry import Source, legacy_source_checksum, register_space
from services.core.settings import Settings, load_settings
from services.core.storage import ObjectStore
from services.embedded.ctrl_c import raise_if_interrupted
from services.embedded.pool import STATE_DIR, LocalPool, WorkerConfig, WorkerMessage, cpu_count
from services.embedded.report import Progress, build_report, print_report
from services.scheduler.loop import Scheduler, loaded_space_key
from services.scheduler.transport import QueueTransport
from services.worker.inputs.loaded_cache import keep_loaded
from services.worker.run.heartbeat import expire_leases

OWNER = "local"
SPACES_PREFIX = ".omnidata/spaces"
TICK_S = 0.1  # scheduler ticks at most 10 times a second (planning, dispatch, reaper, completion)
# ... and at most TICK_CPU_SHARE of one core: a tick costs tens of milliseconds of CPU (SQLite scans through
# the ORM) whatever the job's size, and with one core the workers pay for it (issue 20: ~0.1-0.3 CPU-s per
# view at 10 ticks a second). A slower tick starves nobody: the dispatch window holds seconds of work per
# worker.
TICK_CPU_SHARE = 0.05
TICK_MAX_S = 1.0  # the slowest rate, so a finished job or a dead worker is still seen within a second
SHORT_QUEUE_PER_WORKER = 2  # a worker's message brings a tick only when its queue is this short (or nearly)
SECRET_SETTINGS = {"api_tokens", "secret_key", "aws_access_key_id", "aws_secret_access_key"}
# On a GPU, one renderer per 8 workers: on an H200 with 16 vCPUs (ICL, 132 views, bench/results/gpu.json), 2
# of 16 rendering ran 10.6 views/s end to end against 7.4 with all 16 rendering (each paying its own context).
WORKERS_PER_GPU_RENDERER = 8


def embedded_settings(out: Path, workers: int, render_workers: int | None = None) -> Settings:
    """Settings of the embedded mode: SQLite and the object folder in DIR, whatever OMNIDATA_* says;
    `render_workers` (--render-workers) overrides OMNIDATA_RENDER_WORKERS, and with neither a GPU machine gets
    gpu_renderers' and CPU cores None: every worker renders and derives its own views (on two cores a
    180-view job ran 1.27-1.46x faster that way than with one renderer and one deriver:
    bench/render/render_workers.py)."""
    state = out / STATE_DIR
    chosen = {} if render_workers is None else {"render_workers": render_workers}
    settings = load_settings(
        data_dir=str(state), database_url=f"sqlite:///{state / 'state.db'}", storage_url=str(out),
        dispatch_window=max(128, 64 * workers), env="development", **chosen,
    )
    if settings.render_workers is None:
        gpu = gpu_renderers(workers) if settings.render_device != "cpu" else None
        return settings.model_copy(update={"render_workers": gpu})
    return settings


def gpu_renderers(workers: int) -> int | None:
    """How many of W workers render on a machine with an NVIDIA GPU (None: no GPU, every worker renders). Each
    renderer opens its own device context, loads the kernels and uploads the scene (~1.5-4 s of a core on an
    H200); the others derive."""
    if workers < 2 or not gpu_devices.nvidia_gpus():
        return None
    return max(1, workers // WORKERS_PER_GPU_RENDERER)


def job_fingerprint(spec: JobSpec, checksums: Sequence[str]) -> str:
    """sha256 of the canonical spec and the space checksums (in order): the same request gives the same
    job."""
    doc = json.dumps({"spec": spec.model_dump(mode="json"), "spaces": list(checksums)}, sort_keys=True)
    return hashlib.sha256(doc.encode()).hexdigest()


def find_spaces(session: Session, sources: list[Source]) -> dict[str, Space]:
    """Registered spaces of this folder by name; Conflict when one has the same name but other content."""
    rows = {space.name: space for space in session.scalars(select(Space).where(Space.owner == OWNER))}
    found = {}
    for src in sources:
        space = rows.get(src.name)
        if space is None:
            continue
        if space.checksum != src.checksum and space.checksum != legacy_source_checksum(src.path):
            raise Conflict(
                f"the output folder already holds a different space named {src.name!r} (its files changed); "
                "use a new --out folder"
            )
        found[src.name] = space
        src.checksum = space.checksum  # the same files, zipped as an earlier version did: that job resumes
        src.has_semantics = bool(space.has_semantics)
    return found


def find_job(session: Session, spec: JobSpec, sources: list[Source]) -> Job | None:
    """The newest job of this folder made from the same spec and spaces (not cancelled), or None."""
    want = job_fingerprint(spec, [s.checksum for s in sources])
    for job in session.scalars(
        select(Job).where(Job.owner == OWNER, Job.state != JobState.CANCELLED).order_by(Job.id.desc())
    ):
        try:
            job_spec = JobSpec.model_validate(job.spec)
        except ValueError:
            continue
        checksums = [space.checksum for _job_space, space in job_spaces(session, job.id)]
        if job_fingerprint(job_spec, checksums) == want:
            return job
    return None


@dataclass
class Prepared:
    """The job to run and what resuming it did."""

    job_id: int
    resumed: bool
    requeued: int = 0  # interrupted tasks put back to pending
    redo: int = 0  # done tasks whose file was missing
    retried: int = 0  # failed tasks given another chance
    # spaces validated by this run, for the scheduler to plan from (`Scheduler(loaded_spaces=...)`): one parse
    loaded: dict[str, LoadedSpace] = field(default_factory=dict)


def prepare_job(
    sessions: sessionmaker[Session], store: ObjectStore, spec: JobSpec, sources: list[Source]
) -> Prepared:
    """Register the spaces and create the job, or find the same job again and make it resumable."""
    with sessions() as s:
        spaces = find_spaces(s, sources)
        job = find_job(s, spec, sources) if len(spaces) == len(sources) else None
        if job is not None:
            done = reopen_job(s, store, job)
            s.commit()
            return Prepared(
                job.id, resumed=True, requeued=done.requeued, redo=done.redo, retried=done.retried
            )
        # A new request in this folder: unfinished jobs of earlier requests stop (their files stay).
        for old in s.scalars(select(Job).where(Job.owner == OWNER, Job.state.not_in(JOB_TERMINAL_STATES))):
            cancel_job(s, old)
        ordered, loaded = [], {}
        for src in sources:
            space = spaces.get(src.name)
            if space is None:
                space = register_space(s, store, owner=OWNER, name=src.name, source_path=src.path,
                                    key_prefix=SPACES_PREFIX, **spec.space_frame(), loaded=src.loaded)
            # the scheduler plans from it, then drops it (the workers load their own)
            if src.loaded is not None:
                loaded[loaded_space_key(space.checksum, spec.space_frame())] = src.loaded
            src.loaded = None
            ordered.append(space)
        try:
            job = create_job(s, owner=OWNER, spec=spec, spaces=ordered, output_root="")
        except ValueError as e:
            raise Invalid(str(e)) from None
        s.commit()
        return Prepared(job.id, resumed=False, loaded=loaded)


def run_until_final(sessions: sessionmaker[Session], sched: Scheduler, pool: LocalPool, job_id: int,
                    bar: Progress | None = None, *, timeout: float | None = None) -> tuple[str, float | None]:
    """Tick the scheduler until the job is final; keep the pool full and the bar fresh.

    Returns (final state, time.monotonic() when the job's planning finished, or None if it was planned
    before). Ticks are rate-limited because on a small machine the loop competes with the workers for the CPU;
    the dispatch window is wide enough that workers never wait for a tick. Between workers' messages nothing
    the tick reads changes (this run holds the only job and the only workers of its folder), so then it ticks
    only every TICK_MAX_S (a dead worker, the reaper); a message (a task's outcome, a worker ready) while the
    workers' queue runs short, a worker recycling (until it is replaced) or a busy tick brings the next tick
    at the rate-limited pace. Once the job is past planning, the planning step is skipped.
    """
    bar = bar or Progress(False)
    planned_at: float | None = None
    deadline = None if timeout is None else time.monotonic() + timeout
    next_tick = 0.0  # the earliest next tick (rate limit) ...
    quiet_until = 0.0  # ... and the latest, when no worker has reported since the last one
    changed = True
    plan = True
    recycling = 0  # workers that said they exit (memory or task limit), not yet replaced
    while True:
        # a Ctrl-C a finalizer dropped (generate latches SIGINT: services.embedded.ctrl_c)
        raise_if_interrupted()
        now = time.monotonic()
        if now >= next_tick and (changed or now >= quiet_until):
            cpu0 = time.process_time()
            try:
                res = sched.tick(plan=plan)
            except OperationalError as exc:
                if not disk_full(exc):
                    raise
                # --out's disk holds the run's database too: wait for space, as the workers' writes do
                bar.waiting(f"storage full: no space left for the run's database in {STATE_DIR}")
                next_tick = quiet_until = time.monotonic() + TICK_MAX_S
                continue
            if job_id in res.planned:
                planned_at = time.monotonic()
            with sessions() as s:
                job = s.get(Job, job_id)
                assert job is not None
                state = job.state
                bar.update(sessions, job, final=state in JOB_TERMINAL_STATES)
            if state in JOB_TERMINAL_STATES:
                return state, planned_at
            plan = state in (JobState.PENDING, JobState.PLANNING)
            dead = pool.replace_dead()
            if dead:
                expire_leases(sessions, dead)
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} did not finish in {timeout} s")
            recycling = max(0, recycling - len(dead))
            changed = res.busy or plan or bool(dead) or recycling > 0
            done = time.monotonic()
            next_tick = done + (0.0 if res.busy else tick_interval(time.process_time() - cpu0))
            quiet_until = max(next_tick, done + TICK_MAX_S)
        wake = next_tick if changed else quiet_until
        msgs = pool.drain(max(0.0, wake - time.monotonic()))
        recycling += sum(1 for m in msgs if m[0] == "recycle")  # exiting: ticks at pace until it is replaced
        if msgs and (_short_of_work(pool) or recycling or _handed_off(pool, msgs)):
            changed = True


def disk_full(exc: OperationalError) -> bool:
    """Whether SQLite refused a write for want of disk space (SQLITE_FULL)."""
    return getattr(exc.orig, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL


def _short_of_work(pool: LocalPool) -> bool:
    """Whether the workers' queue holds at most SHORT_QUEUE_PER_WORKER tasks each: then a tick may dispatch
    more, or find the job done (it cannot be while tasks wait in the queue; the quiet tick is the safety
    net)."""
    try:
        return pool.queues.waiting() <= SHORT_QUEUE_PER_WORKER * max(1, len(pool.procs))
    except NotImplementedError:  # macOS: no qsize
        return True


def _handed_off(pool: LocalPool, msgs: list[WorkerMessage]) -> bool:
    """Whether a renderer handed a view off (a `passes` task done, with renderers of their own): its derived
    tasks wait for a tick to be queued, and the render queue's backlog would otherwise keep ticks at
    TICK_MAX_S while the derivers idle."""
    return pool.queues.split and any(m[0] == "outcome" and m[4] == "passes" and m[3] == "done" for m in msgs)


def tick_interval(tick_cpu_s: float) -> float:
    """Seconds until the next tick after one that took `tick_cpu_s` CPU seconds (TICK_CPU_SHARE of a core)."""
    return min(TICK_MAX_S, max(TICK_S, tick_cpu_s / TICK_CPU_SHARE))


def worker_pool(out: Path, settings: Settings, workers: int) -> LocalPool:
    """The W local worker processes of a run on --out (not started), each with its share of the cores; R of
    them render when settings.render_workers says R < W (services.embedded.pool)."""
    threads = max(1, cpu_count() // workers)
    conf = WorkerConfig(out=str(out), settings=settings.model_dump(mode="json", exclude=SECRET_SETTINGS),
                        render_threads=threads, parent_pid=os.getpid(), run=uuid.uuid4().hex)
    return LocalPool(workers, conf, render_workers=settings.render_workers)


def drive(
    sessions: sessionmaker[Session], store: ObjectStore, settings: Settings, out: Path, job_id: int,
    workers: int,
    *,
    progress: bool, loaded_spaces: dict[str, LoadedSpace] | None = None, pool: LocalPool | None = None,
) -> int:
    """Run the scheduler loop with W local workers until the job is final; returns the exit status.
    `loaded_spaces`: spaces this run has loaded already (Prepared.loaded), planned without a second parse.
    `pool`: workers started held (LocalPool.start(held=True)) while the caller prepared the job; released
    here, and stopped when the job is final."""
    with sessions() as s:
        job = s.get(Job, job_id)
        assert job is not None
        if job.state in JOB_TERMINAL_STATES:  # nothing to redo: make sure the job files are there and report
            if not (store.exists(MANIFEST_KEY) and store.exists(JOB_JSON_KEY)):
                write_job_files(s, store, job)
            rep = build_report(sessions, store, job_id)
            print_report(rep, out)
            return 0 if rep.ok else 1

    cache_dir = out / STATE_DIR / "cache"
    # the workers read these instead of parsing the scans again
    for key, loaded in (loaded_spaces or {}).items():
        keep_loaded(cache_dir, key.split(":", 1)[0], loaded)  # key: loaded_space_key(space checksum, frame)
    if pool is None:
        pool = worker_pool(out, settings, workers)
    transport = QueueTransport(pool.queues.derive, pool.queues.render)
    sched = Scheduler(sessions, store, transport, settings, scheduler_id=f"generate:{os.getpid()}",
                      cache_dir=cache_dir, loaded_spaces=loaded_spaces)
    bar = Progress(progress)
    try:
        if pool.procs:
            pool.release()
        else:
            pool.start()
        run_until_final(sessions, sched, pool, job_id, bar)
    except KeyboardInterrupt:
        bar.close()
        print("omnidata generate: interrupted; stopping workers (run the same command again to resume)",
              file=sys.stderr)
        pool.stop()
        with sessions() as s:
            requeue_inflight(s, job_id)
            s.commit()
        return 130
    finally:
        bar.close()
        pool.stop()
    rep = build_report(sessions, store, job_id)
    print_report(rep, out)
    return 0 if rep.ok else 1
