"""`omnidata generate SPACE [SPACE ...] --out DIR`: plan and render a dataset on this machine, no services.

The embedded default of DESIGN.md sections 1 and 8, composed from the SAME parts as the service: SQLite at
DIR/.omnidata/state.db, a LocalStore rooted at DIR (space sources under `.omnidata/spaces`, outputs with an empty
output root), the scheduler's planning/dispatch/reaper/completion loop in this process, and W local worker
processes (spawned) each running the worker's TaskRunner. A multiprocessing queue replaces Redis.

At the end DIR holds `<cue>/<component>/<space>/point_<p>_view_<v>_domain_<cue>.<ext>`, `manifest.jsonl` and
`job.json`. Exit status: 0 when every requested output exists; 1 with a summary of what failed; 2 for bad input
(nothing is created); 130 on Ctrl-C (writes are atomic; run the same command again to resume: the same job is
reused, interrupted tasks go back to pending, missing files are made again, nothing else renders).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import multiprocessing as mp
import os
import queue
import re
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.cli import CliError
from services.frame_args import add_frame_arguments, frame_overrides

log = logging.getLogger("omnidata.generate")

OWNER = "local"
STATE_DIR = ".omnidata"
SPACES_PREFIX = ".omnidata/spaces"
FINAL_STATES = ("done", "failed", "cancelled")
STOP_GRACE_S = 5.0  # a worker finishing its task on Ctrl-C gets this long before it is terminated
VIEWS_REFRESH_S = 2.0
TICK_S = 0.1  # scheduler ticks at most 10 times a second (planning, dispatch, reaper, completion)


# ---------------------------------------------------------------------------------------------- arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata generate` (DESIGN.md section 8)."""
    parser.add_argument("spaces", nargs="+", metavar="SPACE",
                        help="mesh file (.obj with .mtl/textures, .ply, .glb/.gltf) or a folder or .zip holding one")
    parser.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder (created; reused to resume)")
    parser.add_argument("--spec", metavar="job.yaml", help="JobSpec as YAML or JSON; the options below override it")
    parser.add_argument("--cues", metavar="a,b,...", help="cues to produce (default: all the spaces support)")
    parser.add_argument("--points", type=int, metavar="N", help="points of interest per space (points.count)")
    parser.add_argument("--min-views", type=int, metavar="K", help="views a point needs (points.min_views)")
    parser.add_argument("--resolution", type=int, metavar="R", help="square image size in pixels")
    parser.add_argument("--seed", type=int, metavar="S", help="random seed (same seed, same inputs: same outputs)")
    parser.add_argument("--workers", type=int, metavar="W", help="local worker processes (default: CPU cores)")
    parser.add_argument("--name", metavar="COMPONENT", help="component name in the output layout (spec name)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")
    add_frame_arguments(parser)


def cpu_count() -> int:
    """CPU cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _format_validation(e: Any) -> str:
    parts = []
    for err in e.errors():
        loc = ".".join(str(x) for x in err.get("loc", ()) if x != "__root__")
        msg = str(err.get("msg", "")).removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def build_spec(args: argparse.Namespace) -> Any:
    """The JobSpec from --spec and the command-line overrides; CliError naming the problem."""
    import yaml
    from pydantic import ValidationError

    from services.core.jobspec import JobSpec

    data: dict[str, Any] = {}
    if args.spec:
        path = Path(args.spec)
        if not path.is_file():
            raise CliError(f"--spec {args.spec}: no such file")
        try:
            loaded = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as e:
            raise CliError(f"--spec {args.spec}: not valid YAML/JSON ({e})") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise CliError(f"--spec {args.spec}: must hold a mapping of JobSpec fields, got {type(loaded).__name__}")
        data = loaded
    if args.cues is not None:
        data["cues"] = [c.strip() for c in args.cues.split(",") if c.strip()]
    if args.points is not None:
        data.setdefault("points", {})["count"] = args.points
    if args.min_views is not None:
        data.setdefault("points", {})["min_views"] = args.min_views
    if args.resolution is not None:
        data.setdefault("views", {})["resolution"] = args.resolution
    if args.seed is not None:
        data["seed"] = args.seed
    if args.name is not None:
        data["name"] = args.name
    data.update(frame_overrides(args))
    try:
        return JobSpec.model_validate(data)
    except ValidationError as e:
        raise CliError(f"invalid job spec: {_format_validation(e)}") from None


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def space_name(path: Path) -> str:
    """The space's name in the output layout: the folder name, or the file name without its extension."""
    raw = path.name if path.is_dir() else path.stem
    name = _UNSAFE.sub("_", raw).strip("._-") or "space"
    return name[:128]


@dataclass
class Source:
    """One SPACE argument: its path, name, and the checksum its registered source will have."""

    path: Path
    name: str
    checksum: str
    has_semantics: bool | None = None  # known once validated (None: already registered, trusted)
    loaded: Any = None  # the validated LoadedSpace, handed to register_space so the mesh loads once


def source_checksum(path: Path) -> str:
    """sha256 of the object register_space stores for `path` (the file itself, or its deterministic zip)."""
    from services.core.space_registry import pack_source
    from services.core.spaces import resolve_source, sha256_file

    with tempfile.TemporaryDirectory(prefix="omnidata-generate-") as tmp:
        work = Path(tmp)
        mesh = resolve_source(path, work / "x") if path.suffix.lower() == ".zip" else resolve_source(path)
        return sha256_file(pack_source(path, mesh, work))


def check_sources(paths: Sequence[str]) -> list[Source]:
    """Each SPACE exists, holds exactly one mesh and has a distinct name; CliError otherwise."""
    from services.core.spaces import SpaceError

    sources: list[Source] = []
    for raw in paths:
        p = Path(raw).expanduser()
        if not p.exists():
            raise CliError(f"{raw}: no such file or folder")
        try:
            checksum = source_checksum(p.resolve())
        except SpaceError as e:
            raise CliError(str(e)) from None
        sources.append(Source(p.resolve(), space_name(p), checksum))
    names = [s.name for s in sources]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CliError(f"two spaces would share the name {dup[0]!r} in the output layout; rename one")
    return sources


def validate_sources(sources: list[Source], spec: Any) -> None:
    """Load every (not yet registered) space and check it can give the requested cues; CliError otherwise."""
    from services.core.jobspec import cues_for_space
    from services.core.spaces import SpaceError, load_space

    for src in sources:
        if src.has_semantics is not None:
            continue
        try:
            loaded = load_space(src.path, **spec.space_frame())
        except SpaceError as e:
            raise CliError(str(e)) from None
        src.loaded = loaded
        src.has_semantics = bool(loaded.has_semantics)
        try:
            cues_for_space(spec, has_semantics=src.has_semantics)
        except ValueError as e:
            raise CliError(f"space {src.name!r}: {e}") from None


# ---------------------------------------------------------------------------------------------- the job


def embedded_settings(out: Path, workers: int) -> Any:
    """Settings of the embedded mode: SQLite and the object folder in DIR, whatever OMNIDATA_* says."""
    from services.core.settings import load_settings

    state = out / STATE_DIR
    return load_settings(
        data_dir=str(state), database_url=f"sqlite:///{state / 'state.db'}", storage_url=str(out),
        dispatch_window=max(64, 32 * workers), env="development",
    )


def job_fingerprint(spec: Any, checksums: Sequence[str]) -> str:
    """sha256 of the canonical spec and the space checksums (in order): the same request gives the same job."""
    doc = json.dumps({"spec": spec.model_dump(mode="json"), "spaces": list(checksums)}, sort_keys=True)
    return hashlib.sha256(doc.encode()).hexdigest()


def find_spaces(session: Any, sources: list[Source]) -> dict[str, Any]:
    """Registered spaces of this folder by name; CliError when one has the same name but other content."""
    from sqlalchemy import select

    from services.core.models import Space

    rows = {sp.name: sp for sp in session.scalars(select(Space).where(Space.owner == OWNER))}
    found = {}
    for src in sources:
        sp = rows.get(src.name)
        if sp is None:
            continue
        if sp.checksum != src.checksum:
            raise CliError(
                f"the output folder already holds a different space named {src.name!r} (its files changed); "
                "use a new --out folder"
            )
        found[src.name] = sp
        src.has_semantics = bool(sp.has_semantics)
    return found


def find_job(session: Any, spec: Any, sources: list[Source]) -> Any:
    """The newest job of this folder made from the same spec and spaces (not cancelled), or None."""
    from sqlalchemy import select

    from services.core.jobs import job_spaces
    from services.core.jobspec import JobSpec
    from services.core.models import Job

    want = job_fingerprint(spec, [s.checksum for s in sources])
    for job in session.scalars(select(Job).where(Job.owner == OWNER, Job.state != "cancelled").order_by(Job.id.desc())):
        try:
            job_spec = JobSpec.model_validate(job.spec)
        except ValueError:
            continue
        checksums = [sp.checksum for _js, sp in job_spaces(session, job.id)]
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


def prepare_job(sm: Any, store: Any, spec: Any, sources: list[Source]) -> Prepared:
    """Register the spaces and create the job, or find the same job again and make it resumable."""
    from services.core.jobs import cancel_job, create_job
    from services.core.models import Job
    from services.core.space_registry import register_space
    from services.core.spaces import SpaceError

    with sm() as s:
        spaces = find_spaces(s, sources)
        job = find_job(s, spec, sources) if len(spaces) == len(sources) else None
        if job is not None:
            prepared = resume_job(s, store, job)
            s.commit()
            return prepared
        # A new request in this folder: unfinished jobs of earlier requests stop (their files stay).
        from sqlalchemy import select

        for old in s.scalars(select(Job).where(Job.owner == OWNER, Job.state.not_in(FINAL_STATES))):
            cancel_job(s, old)
        ordered = []
        for src in sources:
            sp = spaces.get(src.name)
            if sp is None:
                try:
                    sp = register_space(s, store, owner=OWNER, name=src.name, source_path=src.path,
                                        key_prefix=SPACES_PREFIX, **spec.space_frame(),
                                        loaded=src.loaded)
                except SpaceError as e:
                    raise CliError(str(e)) from None
            src.loaded = None  # the workers load their own copy; do not keep the mesh in this process
            ordered.append(sp)
        try:
            job = create_job(s, owner=OWNER, spec=spec, spaces=ordered, output_root="")
        except ValueError as e:
            raise CliError(str(e)) from None
        s.commit()
        return Prepared(job.id, resumed=False)


def resume_job(s: Any, store: Any, job: Any) -> Prepared:
    """Make a job of an earlier run resumable: in-flight tasks back to pending, missing outputs redone."""
    from sqlalchemy import func, select

    from services.core.cues import CATALOG
    from services.core.db import transition
    from services.core.jobs import retry_failed
    from services.core.models import Task

    prepared = Prepared(job.id, resumed=True)
    if job.state == "planning":  # interrupted while planning: plan again from scratch
        job.state, job.planner, job.planner_lease_until = "pending", None, None
        s.flush()
        return prepared
    if job.state == "pending":
        return prepared
    if job.state == "paused":
        job.state = "running"
    # Interrupted tasks: the attempt did not fail, so it does not count.
    running = [i for (i,) in s.execute(select(Task.id).where(Task.job_id == job.id, Task.state == "running"))]
    prepared.requeued += len(transition(
        s, job_id=job.id, task_ids=running, from_state="running", to_state="pending",
        attempts=func.max(Task.attempts - 1, 0), worker_id=None, lease_until=None, queued_at=None, not_before=None,
    ))
    queued = [i for (i,) in s.execute(select(Task.id).where(Task.job_id == job.id, Task.state == "queued"))]
    prepared.requeued += len(transition(
        s, job_id=job.id, task_ids=queued, from_state="queued", to_state="pending", queued_at=None,
    ))
    # Done outputs whose file is gone are made again (the internal pass cache is rebuilt on demand).
    internal = [n for n, c in CATALOG.items() if c.internal]
    missing = [
        tid for tid, key in s.execute(
            select(Task.id, Task.output_key).where(
                Task.job_id == job.id, Task.state == "done", Task.cue.not_in(internal)
            )
        )
        if not key or not store.exists(key)
    ]
    prepared.redo = len(transition(
        s, job_id=job.id, task_ids=missing, from_state="done", to_state="pending",
        attempts=0, error=None, output_key=None, size=None, sha256=None, finished_at=None, not_before=None,
    ))
    if job.state in ("done", "failed", "running"):
        prepared.retried = retry_failed(s, job)
    if prepared.redo and job.state in ("done", "failed"):
        job.state, job.error, job.finished_at = "running", None, None
    s.flush()
    return prepared


# ---------------------------------------------------------------------------------------------- local workers


class QueueTransport:
    """The scheduler's Transport for local workers: task ids into a multiprocessing queue."""

    def __init__(self, q: Any) -> None:
        self.q = q
        self.sent = 0

    def send(self, batch: Sequence[tuple[int, str]]) -> None:
        """Put one task id per message on the queue."""
        for task_id, _cue in batch:
            self.q.put(int(task_id))
        self.sent += len(batch)


@dataclass(frozen=True)
class WorkerConfig:
    """What a local worker process needs (plain data: it crosses a spawn)."""

    out: str
    settings: dict[str, Any]
    render_threads: int
    parent_pid: int
    log_level: int = logging.WARNING


def worker_main(conf: WorkerConfig, tasks: Any, results: Any, stop: Any) -> None:
    """Body of a local worker process: take task ids from `tasks`, run them, report outcomes on `results`."""
    # Ctrl-C reaches the whole process group: the parent decides when workers stop. SIGTERM (sent when
    # the grace period is over) unwinds the stack, so an in-flight write removes its temporary file.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    # W workers share the cores: numeric libraries get the same thread budget as Cycles (set before numpy loads).
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ.setdefault(var, str(conf.render_threads))
    logging.basicConfig(level=conf.log_level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    from services.core.db import make_engine, make_sessionmaker
    from services.core.settings import get_settings
    from services.core.storage import LocalStore
    from services.worker.heartbeat import Heartbeat
    from services.worker.runner import TaskRunner, TransientError

    settings = get_settings(**conf.settings)
    engine = make_engine(settings.database_url)
    sm = make_sessionmaker(engine)
    store = LocalStore(conf.out)
    worker_id = f"{socket.gethostname()}:{os.getpid()}"
    hb = Heartbeat(sm, worker_id, queues=["local"], lease_s=settings.lease_s).start()
    runner = TaskRunner(sm, store, settings, worker_id, heartbeat=hb, cache_dir=Path(conf.out) / STATE_DIR / "cache",
                        render_threads=conf.render_threads)
    results.put(("ready", os.getpid(), worker_id))
    try:
        while not stop.is_set():
            if os.getppid() != conf.parent_pid:  # the parent died: do not linger as an orphan
                break
            try:
                task_id = tasks.get(timeout=0.5)
            except queue.Empty:
                continue
            if task_id is None:
                break
            try:
                o = runner.run(int(task_id))
            except TransientError as e:  # the database was busy for a long time: try the message again later
                log.warning("task %s: %s", task_id, e)
                time.sleep(1.0)
                tasks.put(task_id)
                continue
            results.put(("outcome", os.getpid(), o.task_id, o.status, o.cue, o.labels, o.error))
            if o.recycle:  # memory or task limit: exit, the parent starts a fresh process
                results.put(("recycle", os.getpid(), worker_id))
                break
    finally:
        hb.stop(timeout=1.0)
        runner.close()
        engine.dispose()
        results.close()
        results.join_thread()  # our messages are flushed before we leave
    # Skip interpreter teardown: Blender's static destructors only print noise ("Freeing memory after the
    # leak detector has run") and nothing is left to flush.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


@dataclass
class LocalPool:
    """W worker processes (spawn context) fed by one task queue; dead or recycled ones are replaced."""

    size: int
    conf: WorkerConfig
    ctx: Any = field(default_factory=lambda: mp.get_context("spawn"))
    procs: list[Any] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.tasks = self.ctx.Queue()
        self.results = self.ctx.Queue()
        self.stop_event = self.ctx.Event()
        self.worker_ids: dict[int, str] = {}
        self.started = 0
        self.stopped = False

    def _spawn(self) -> None:
        p = self.ctx.Process(target=worker_main, args=(self.conf, self.tasks, self.results, self.stop_event),
                             name=f"omnidata-worker-{self.started}", daemon=False)
        p.start()
        self.started += 1
        self.worker_ids[p.pid] = f"{socket.gethostname()}:{p.pid}"
        self.procs.append(p)

    def start(self) -> None:
        """Start the workers."""
        for _ in range(self.size):
            self._spawn()

    def replace_dead(self) -> list[str]:
        """Start a new process for each one that exited; returns the worker ids of those that exited."""
        gone = []
        for p in list(self.procs):
            if not p.is_alive():
                p.join(0)
                self.procs.remove(p)
                gone.append(self.worker_ids.get(p.pid, f"{socket.gethostname()}:{p.pid}"))
                self._spawn()
        return gone

    def drain(self, timeout: float) -> list[tuple[Any, ...]]:
        """Messages from workers: waits up to `timeout` for the first one, then takes what is there."""
        msgs = []
        try:
            msgs.append(self.results.get(timeout=timeout))
            while True:
                msgs.append(self.results.get_nowait())
        except queue.Empty:
            pass
        return msgs

    def stop(self, grace: float = STOP_GRACE_S) -> None:
        """Ask every worker to stop after its task; terminate those still busy after `grace` seconds."""
        if self.stopped:
            return
        self.stopped = True
        self.stop_event.set()
        for _ in self.procs:
            try:
                self.tasks.put_nowait(None)
            except Exception:
                pass
        deadline = time.monotonic() + grace
        for p in self.procs:
            p.join(max(0.0, deadline - time.monotonic()))
        for p in self.procs:
            if p.is_alive():
                p.terminate()
        for p in self.procs:
            p.join(3.0)
            if p.is_alive():
                p.kill()
                p.join(1.0)
        self.procs.clear()
        for q in (self.tasks, self.results):
            q.cancel_join_thread()  # do not block exit on messages nobody will read
            q.close()


def requeue_inflight(sm: Any, job_id: int) -> int:
    """After stopping the workers: queued and running tasks of the job back to pending (attempt not counted)."""
    from sqlalchemy import func, select

    from services.core.db import transition
    from services.core.models import Task

    with sm() as s:
        n = 0
        for state in ("running", "queued"):
            ids = [i for (i,) in s.execute(select(Task.id).where(Task.job_id == job_id, Task.state == state))]
            extra: dict[str, Any] = {"queued_at": None}
            if state == "running":
                extra.update(attempts=func.max(Task.attempts - 1, 0), worker_id=None, lease_until=None)
            n += len(transition(s, job_id=job_id, task_ids=ids, from_state=state, to_state="pending", **extra))
        s.commit()
        return n


# ---------------------------------------------------------------------------------------------- progress


class Progress:
    """A tqdm bar on stderr: labels done of the total, labels/s, ETA, and views finished."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar: Any = None
        self._views_at = 0.0
        self.views_text = ""

    def update(self, sm: Any, job: Any, *, final: bool = False) -> None:
        """Refresh from the job's counters (and, every few seconds or at the end, the number of finished views)."""
        from services.core.cues import CATALOG
        from services.core.db import job_progress

        if not self.enabled:
            return
        with sm() as s:
            prog = job_progress(s, job.id)
            now = time.monotonic()
            if final or now - self._views_at > VIEWS_REFRESH_S:
                self._views_at = now
                done, total = views_done(s, job.id)
                self.views_text = f"views {done}/{total}"
        total = sum(n for cue, st in prog.items() if not CATALOG[cue].internal for st_name, n in st.items()
                    if st_name != "cancelled")
        done = sum(st.get("done", 0) for cue, st in prog.items() if not CATALOG[cue].internal)
        if total == 0:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, unit="label", file=sys.stderr, dynamic_ncols=True,
                            mininterval=0.5, desc="generate")
        self.bar.total = total
        self.bar.set_postfix_str(self.views_text, refresh=final)
        if done > self.bar.n:
            self.bar.update(done - self.bar.n)  # redraws at most every mininterval

    def close(self) -> None:
        """Finish the bar."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def views_done(s: Any, job_id: int) -> tuple[int, int]:
    """(views whose every task is done, views planned)."""
    from sqlalchemy import case, func, select

    from services.core.models import Task, View

    total = int(s.scalar(select(func.count()).select_from(View).where(View.job_id == job_id)) or 0)
    per_view = (
        select(Task.space_id, Task.point_idx, Task.view_idx)
        .where(Task.job_id == job_id)
        .group_by(Task.space_id, Task.point_idx, Task.view_idx)
        .having(func.sum(case((Task.state == "done", 0), else_=1)) == 0)
        .subquery()
    )
    done = int(s.scalar(select(func.count()).select_from(per_view)) or 0)
    return done, total


# ---------------------------------------------------------------------------------------------- report


@dataclass
class Report:
    """How a run ended."""

    state: str
    outputs: int = 0
    views: int = 0
    missing: list[str] = field(default_factory=list)
    failed: dict[str, tuple[int, str]] = field(default_factory=dict)  # cue -> (count, first error)
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Every requested output exists."""
        return self.state == "done" and not self.missing and not self.failed


def build_report(sm: Any, store: Any, job_id: int) -> Report:
    """Check every requested output against the folder and collect failures (cue, count, first error)."""
    from sqlalchemy import select

    from services.core.cues import CATALOG
    from services.core.models import Job, Task, View

    internal = [n for n, c in CATALOG.items() if c.internal]
    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None
        rep = Report(state=job.state, error=job.error)
        rep.views = len(s.execute(select(View.point_idx).where(View.job_id == job_id)).all())
        rows = s.execute(
            select(Task.cue, Task.state, Task.output_key, Task.error, Task.point_idx, Task.view_idx)
            .where(Task.job_id == job_id, Task.cue.not_in(internal)).order_by(Task.id)
        ).all()
        # Failed internal tasks (a render that kept failing) explain the missing outputs that depend on them.
        failed_internal = s.execute(
            select(Task.cue, Task.error).where(Task.job_id == job_id, Task.state == "failed", Task.cue.in_(internal))
            .order_by(Task.id)
        ).all()
    for cue, state, key, error, p, v in rows:
        if state == "done" and key and store.exists(key):
            rep.outputs += 1
            continue
        if state == "failed":
            n, first = rep.failed.get(cue, (0, (error or "no error recorded")))
            rep.failed[cue] = (n + 1, first)
        else:
            rep.missing.append(f"{cue} point {p} view {v} ({state})")
    for cue, error in failed_internal:
        n, first = rep.failed.get(cue, (0, error or "no error recorded"))
        rep.failed[cue] = (n + 1, first)
    return rep


def print_report(rep: Report, out: Path) -> None:
    """What was written, or what failed (cue, count, first error) on stderr."""
    if rep.ok:
        print(f"omnidata generate: {rep.outputs} files for {rep.views} views in {out} "
              "(manifest.jsonl, job.json)")
        return
    print(f"omnidata generate: job {rep.state}; {rep.outputs} outputs written to {out}", file=sys.stderr)
    if rep.error and not rep.failed:
        print(f"  {rep.error}", file=sys.stderr)
    for cue, (n, first) in sorted(rep.failed.items()):
        print(f"  {cue}: {n} failed; first error: {first.splitlines()[0] if first else ''}", file=sys.stderr)
    if rep.missing:
        shown = ", ".join(rep.missing[:5]) + (f" and {len(rep.missing) - 5} more" if len(rep.missing) > 5 else "")
        print(f"  {len(rep.missing)} outputs missing: {shown}", file=sys.stderr)


# ---------------------------------------------------------------------------------------------- run


def run(args: argparse.Namespace) -> int:
    """Plan and render the dataset into --out; see the module docstring for exit statuses."""
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    for noisy in ("alembic", "trimesh"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    workers = args.workers if args.workers is not None else cpu_count()
    if workers < 1:
        raise CliError(f"--workers must be at least 1, got {workers}")
    spec = build_spec(args)
    sources = check_sources(args.spaces)
    out = Path(args.out).expanduser().resolve()
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {args.out}: exists and is not a folder")
    state_db = out / STATE_DIR / "state.db"

    from services.core.db import make_engine, make_sessionmaker, migrate
    from services.core.storage import LocalStore

    settings = embedded_settings(out, workers)
    if state_db.exists():  # a folder of an earlier run: spaces it already holds need no second validation
        engine = make_engine(settings.database_url)
        migrate(settings.database_url)
        sm = make_sessionmaker(engine)
        with sm() as s:
            find_spaces(s, sources)
        engine.dispose()
    validate_sources(sources, spec)  # loads new spaces: bad input is refused before anything is created

    migrate(settings.database_url)
    engine = make_engine(settings.database_url)
    sm = make_sessionmaker(engine)
    store = LocalStore(out)
    try:
        prepared = prepare_job(sm, store, spec, sources)
        if prepared.resumed:
            print(f"omnidata generate: resuming job {prepared.job_id} in {out} ({prepared.requeued} interrupted, "
                  f"{prepared.redo} missing, {prepared.retried} failed tasks to redo)", file=sys.stderr)
        return drive(sm, store, settings, out, prepared.job_id, workers, progress=not args.no_progress)
    finally:
        engine.dispose()


def run_until_final(sm: Any, sched: Any, pool: LocalPool, job_id: int, bar: Progress | None = None,
                    *, timeout: float | None = None) -> tuple[str, float | None]:
    """Tick the scheduler (at most every TICK_S) until the job is final; keep the pool full and the bar fresh.

    Returns (final state, time.monotonic() when the job's planning finished, or None if it was planned before).
    Ticks are rate-limited because on a small machine the loop competes with the workers for the CPU; the
    dispatch window is wide enough that workers never wait for a tick.
    """
    from services.core.models import Job
    from services.worker.heartbeat import expire_leases

    bar = bar or Progress(False)
    planned_at: float | None = None
    deadline = None if timeout is None else time.monotonic() + timeout
    next_tick = 0.0
    while True:
        now = time.monotonic()
        if now >= next_tick:
            res = sched.tick()
            if job_id in res.planned:
                planned_at = time.monotonic()
            with sm() as s:
                job = s.get(Job, job_id)
                assert job is not None
                state = job.state
                bar.update(sm, job, final=state in FINAL_STATES)
            if state in FINAL_STATES:
                return state, planned_at
            dead = pool.replace_dead()
            if dead:
                expire_leases(sm, dead)
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} did not finish in {timeout} s")
            next_tick = time.monotonic() + (0.0 if res.busy else TICK_S)
        pool.drain(max(0.0, next_tick - time.monotonic()))


def drive(sm: Any, store: Any, settings: Any, out: Path, job_id: int, workers: int, *, progress: bool) -> int:
    """Run the scheduler loop with W local workers until the job is final; returns the exit status."""
    from services.core.keys import JOB_JSON_KEY, MANIFEST_KEY
    from services.core.manifest import write_job_files
    from services.core.models import Job
    from services.scheduler.loop import Scheduler

    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None
        if job.state in FINAL_STATES:  # nothing to redo: make sure the job files are there and report
            if not (store.exists(MANIFEST_KEY) and store.exists(JOB_JSON_KEY)):
                write_job_files(s, store, job)
            rep = build_report(sm, store, job_id)
            print_report(rep, out)
            return 0 if rep.ok else 1

    threads = max(1, cpu_count() // workers)
    conf = WorkerConfig(out=str(out), settings=settings.model_dump(mode="json", exclude={"api_tokens", "secret_key",
                                                                                          "aws_access_key_id",
                                                                                          "aws_secret_access_key"}),
                        render_threads=threads, parent_pid=os.getpid())
    pool = LocalPool(workers, conf)
    transport = QueueTransport(pool.tasks)
    sched = Scheduler(sm, store, transport, settings, scheduler_id=f"generate:{os.getpid()}",
                      cache_dir=out / STATE_DIR / "cache")
    bar = Progress(progress)
    try:
        pool.start()
        run_until_final(sm, sched, pool, job_id, bar)
    except KeyboardInterrupt:
        bar.close()
        print("omnidata generate: interrupted; stopping workers (run the same command again to resume)",
              file=sys.stderr)
        pool.stop()
        requeue_inflight(sm, job_id)
        return 130
    finally:
        bar.close()
        pool.stop()
    rep = build_report(sm, store, job_id)
    print_report(rep, out)
    return 0 if rep.ok else 1
