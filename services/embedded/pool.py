"""Local worker processes of `omnidata generate`: W processes each running the worker's TaskRunner, fed task
ids through a multiprocessing queue (the embedded mode's stand-in for Redis).

Roles (settings.render_workers; services.embedded.job picks R when unset): one worker alone renders and
derives its own views ("all"). With R renderers of W workers, R "render" workers take the render queue's
`passes` tasks first (handing each pass set to whoever derives it: services.worker.run.pass_handoff) and
derive only while no render waits or once their budget of pass sets ahead (TaskQueues), and W - R
"derive" workers take only the derive queue and never load Blender: one device context per renderer on a
GPU, and no Blender start-up in the others.

The first workers are forked from `generate` when that is safe (start_method): they inherit its imports
(numpy, SQLAlchemy, trimesh, pydantic, the domain: ~1 of the ~1.6 CPU-s a spawned worker spends importing) and
import only the worker's own modules and Blender. A replacement (recycled or dead worker) is spawned: by then
the parent has threads and open database connections, which a fork must not copy."""

from __future__ import annotations

import gc
import importlib
import logging
import multiprocessing as mp
import os
import queue
import signal
import socket
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field, replace
from multiprocessing.context import ForkContext, SpawnContext
from multiprocessing.process import BaseProcess
from multiprocessing.queues import Queue
from multiprocessing.synchronize import Event
from pathlib import Path
from typing import TYPE_CHECKING, Literal, NoReturn

from services.core.gc_pause import collections_paused
from services.worker.blender.calls import exit_at_once_inside_blender
from services.worker.blender.threads import remove_session_temp_dir
from services.worker.process.heap import keep_freed_memory
from services.worker.process.numeric_threads import numeric_threads_pinned, pin_numeric_threads
from services.worker.run.stop_signal import stop_within

# imported by the worker after its hold, not here (a spawned worker imports this module first)
if TYPE_CHECKING:
    from services.worker.run.runner import TaskRunner

log = logging.getLogger("omnidata.generate")

STATE_DIR = ".omnidata"  # the embedded mode's state under --out: state.db, space sources, pass cache
STOP_GRACE_S = 5.0  # a worker finishing its task on Ctrl-C gets this long before it is terminated


def cpu_count() -> int:
    """CPU cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


# "all": renders its views and derives them (view batches); "render": takes renders first and hands the views
# off; "derive": only derives, from stored pass sets (module docstring)
Role = Literal["all", "render", "derive"]


@dataclass(frozen=True)
class WorkerConfig:
    """What a local worker process needs (plain data: it crosses a spawn)."""

    out: str
    settings: dict[str, object]  # Settings.model_dump(mode="json"), secrets left out
    render_threads: int
    parent_pid: int
    log_level: int = logging.WARNING
    role: Role = "all"
    run: str = ""  # this run's stamp on the pass sets it hands off (services.worker.run.pass_handoff)


# what a worker reports: ("ready", pid, worker id), ("outcome", pid, task id, status, cue, labels, error) or
# ("recycle", pid, worker id)
WorkerMessage = tuple[object, ...]


def worker_main(conf: WorkerConfig, tasks: TaskQueues, results: Queue[WorkerMessage], stop: Event,
                go: Event) -> None:
    """Body of a local worker process: import what a task needs (Blender, unless it only derives), wait for
    `go`, then take task ids from `tasks`, run them and report outcomes on `results`. Nothing touches the
    state or --out before `go`."""
    # Ctrl-C reaches the whole process group: the parent decides when workers stop. SIGTERM (a held worker
    # stopped, or the stop's grace period over) unwinds the stack, so an in-flight write removes its temporary
    # file; inside Blender (loading, rendering) it ends the worker at once (services.worker.blender.calls).
    # Either way the worker leaves without interpreter teardown, which a spawned worker would otherwise run.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    exit_at_once_inside_blender(signal.SIGTERM)
    code = 0
    try:
        _work(conf, tasks, results, stop, go)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    except Exception as e:
        wrapped = stop_within(e)  # SIGTERM's exit raised while a numba kernel was called comes back wrapped
        if not isinstance(wrapped, SystemExit):
            traceback.print_exc()
        code = wrapped.code if isinstance(wrapped, SystemExit) and isinstance(wrapped.code, int) else 1
    _exit_quietly(code)


def _work(conf: WorkerConfig, tasks: TaskQueues, results: Queue[WorkerMessage], stop: Event,
          go: Event) -> None:
    """worker_main's work: warm up held, then serve tasks once released (returns when stopped or
    recycling)."""
    # before numpy loads (spawned; a forked worker's parent pinned them before it loaded numpy)
    pin_numeric_threads()
    keep_freed_memory()
    logging.basicConfig(level=conf.log_level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    with collections_paused():  # the warm-up's imports (services.core.gc_pause)
        from services.core.db.engine import make_engine, make_sessionmaker
        from services.core.settings import get_settings
        from services.core.storage import LocalStore
        from services.core.user_cache import CURVATURE, user_cache_dir
        from services.worker.run.heartbeat import Heartbeat
        from services.worker.run.pass_handoff import RawPassSets
        from services.worker.run.runner import TaskRunner

        released = _warmed_up_and_released(conf, stop, go)
        gc.freeze()  # the warm-up's objects (Blender, kernels): no later collection walks them (~0.05 CPU-s)
    if not released:
        return
    settings = get_settings(**{**conf.settings, "render_threads": conf.render_threads})
    engine = make_engine(settings.database_url)
    sessions = make_sessionmaker(engine)
    store = LocalStore(conf.out)
    worker_id = f"{socket.gethostname()}:{os.getpid()}"
    hb = Heartbeat(sessions, worker_id, queues=["local"], lease_s=settings.lease_s).start()
    runner = TaskRunner(sessions, store, settings, worker_id, heartbeat=hb,
                        cache_dir=Path(conf.out) / STATE_DIR / "cache",
                        curvature_dir=user_cache_dir(CURVATURE),  # the user's: a later run reads it too
                        hand_off_views=conf.role == "render", pass_sets=RawPassSets(store, conf.run))
    _freeze_long_lived()  # modules, Blender
    results.put(("ready", os.getpid(), worker_id))
    try:
        _serve(runner, conf, tasks, results, stop, worker_id)
    finally:
        hb.stop(timeout=1.0)
        runner.close()
        engine.dispose()
        results.close()
        results.join_thread()  # our messages are flushed before we leave


def _exit_quietly(code: int) -> NoReturn:
    """Leave without interpreter teardown: Blender's static destructors only print noise ("Freeing memory
    after the leak detector has run") and nothing is left to flush but the standard streams, and Blender's
    temp folder to remove."""
    remove_session_temp_dir()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _serve(runner: TaskRunner, conf: WorkerConfig, tasks: TaskQueues, results: Queue[WorkerMessage],
           stop: Event, worker_id: str) -> None:
    """Take task ids from `tasks` and run them until told to stop, the parent dies or the worker should
    recycle."""
    from services.worker.run.claim import TransientError

    first = True
    read = 0  # pass sets this worker has read back (TaskQueues.ahead)
    while not stop.is_set():
        if os.getppid() != conf.parent_pid:  # the parent died: do not linger as an orphan
            return
        try:
            task_id, came_from = tasks.next_for(conf.role)
        except queue.Empty:
            continue
        if task_id is None:
            return
        try:
            o = runner.run(int(task_id))
        except TransientError as e:  # the database was busy for a long time: try the message again later
            log.warning("task %s: %s", task_id, e)
            time.sleep(1.0)
            came_from.put(task_id)
            continue
        for each in o.all():  # the task of the message, then the rest of its view batch
            results.put(
                ("outcome", os.getpid(), each.task_id, each.status, each.cue, each.labels, each.error)
            )
        handed = conf.role == "render" and o.cue == "passes" and o.status == "done"
        tasks.count(handed=int(handed), read=runner.maker.pass_sets_read - read)
        read = runner.maker.pass_sets_read
        if first:  # the space, its plan and the compiled kernels the first view loaded
            _freeze_long_lived()
            first = False
        if o.recycle:  # memory or task limit: exit, the parent starts a fresh process
            results.put(("recycle", os.getpid(), worker_id))
            return


def _freeze_long_lived() -> None:
    """Move every object alive now out of the cyclic collector's reach (gc.freeze): a worker's full
    collections traversed the ~10^6 objects of its imports, Blender and the loaded space each time (~130 ms, 3
    a 66-view run); garbage is still freed by reference counting, and later objects are still collected."""
    gc.collect()
    gc.freeze()


def _warmed_up_and_released(conf: WorkerConfig, stop: Event, go: Event) -> bool:
    """Import Blender for the first render (while the parent validates and plans; not in a worker that only
    derives) and make the kernels' compiler target (its first view would), then wait for `go` (held:
    LocalPool.start(held=True)); False when the pool stopped, or the parent died, first."""
    from services.worker.blender.threads import import_bpy
    from services.worker.process import kernel_target

    if stop.is_set():  # stopped before it began (a finished job resumed): no Blender to load
        return False
    if conf.role != "derive":
        import_bpy(conf.render_threads)
        importlib.import_module("services.worker.blender.scene")
    kernel_target.load()
    while not go.wait(0.2):
        if stop.is_set() or os.getppid() != conf.parent_pid:
            return False
    return True


def start_method(setting: str = "auto") -> str:
    """"fork" when this process can be forked safely for a worker, else "spawn". Safe: fork exists (not
    Windows or macOS's default), the setting allows it, only this thread runs (a lock held by another thread
    would stay held in the child), the numeric libraries were pinned before numpy loaded (a worker's BLAS must
    run one thread, and a forked one keeps its parent's), and Blender is not loaded (its thread pools do not
    survive a
    fork)."""
    if setting != "auto" or "fork" not in mp.get_all_start_methods() or sys.platform == "darwin":
        return "spawn"
    if threading.active_count() > 1 or not numeric_threads_pinned() or "bpy" in sys.modules:
        return "spawn"
    return "fork"


# What a worker imports past its parent's `generate` imports (not Blender): imported once in the parent before
# it forks several workers, instead of once in each (~0.25 CPU-s).
WORKER_MODULES = ("services.worker.run.runner", "services.worker.run.heartbeat", "services.core.storage",
                  "services.core.db.engine")


RENDER_POLL_S = 0.02  # a renderer waiting for derive work looks at the render queue this often
# pass sets the renderers may have handed off and not yet read back (~8 MB each at 512 px, on --out's disk):
# at least this many, and RENDER_AHEAD_PER_DERIVER for each deriver (none waits for a view while one renders)
RENDER_AHEAD_VIEWS = 12
RENDER_AHEAD_PER_DERIVER = 2


def ahead_budget(workers: int, renderers: int) -> int:
    """The pass sets renderers may be ahead of the W - R derivers (RENDER_AHEAD_VIEWS)."""
    return max(RENDER_AHEAD_VIEWS, RENDER_AHEAD_PER_DERIVER * (workers - renderers))


class TaskQueues:
    """The workers' task queues: `derive` holds every task but `passes`, which goes to `render`; without
    renderers of their own (every worker renders) both are one queue. With renderers, `ahead` counts the pass
    sets handed off and not yet read back: a renderer renders ahead of the derivers by at most
    `budget` views (the pass cache's: ahead_budget), and past it derives while derive work waits."""

    def __init__(self, ctx: SpawnContext, split: bool, budget: int = RENDER_AHEAD_VIEWS) -> None:
        self.derive: Queue[int | None] = ctx.Queue()
        self.render: Queue[int | None] = ctx.Queue() if split else self.derive
        self.ahead = ctx.Value("i", 0)
        self.budget = budget

    @property
    def split(self) -> bool:
        return self.render is not self.derive

    def all(self) -> tuple[Queue[int | None], ...]:
        return (self.derive, self.render) if self.split else (self.derive,)

    def count(self, *, handed: int, read: int) -> None:
        """A worker's pass sets handed off and read back since its last count. A killed worker's last reads
        go uncounted: the count errs high, so a renderer derives sooner, but it never idles while a render
        waits and no derive work does."""
        if self.split and (handed or read):
            with self.ahead.get_lock():
                self.ahead.value += handed - read

    def next_for(self, role: Role, timeout: float = 0.5) -> tuple[int | None, Queue[int | None]]:
        """A task id for a worker of `role` and the queue it came from (queue.Empty after `timeout`): a
        renderer takes a waiting render first while within its budget (or when no derive work waits), and
        derives otherwise."""
        if role != "render" or not self.split:
            return self.derive.get(timeout=timeout), self.derive
        # wait on the derive queue in short steps, so a render that comes meanwhile waits at most one step
        deadline = time.monotonic() + timeout
        while True:
            if self.ahead.value < self.budget or self.derive.empty():
                try:
                    return self.render.get_nowait(), self.render
                except queue.Empty:
                    pass
            try:
                return self.derive.get(timeout=RENDER_POLL_S), self.derive
            except queue.Empty:
                if time.monotonic() >= deadline:
                    raise

    def waiting(self) -> int:
        """Task ids waiting in the queues (raises NotImplementedError where qsize does not exist: macOS)."""
        return sum(q.qsize() for q in self.all())


@dataclass
class LocalPool:
    """W worker processes fed by task queues (queues and events of the spawn context, which forked processes
    share as well); dead or recycled ones are replaced in the same role. `render_workers` R < W: R of them
    render (module docstring)."""

    size: int
    conf: WorkerConfig
    render_workers: int | None = None
    ctx: SpawnContext = field(default_factory=lambda: mp.get_context("spawn"))
    procs: list[BaseProcess] = field(default_factory=list)

    def __post_init__(self) -> None:
        split = self.render_workers is not None and self.render_workers < self.size
        self.queues = TaskQueues(self.ctx, split, ahead_budget(self.size, self.render_workers or self.size))
        self.roles: dict[int | None, Role] = {}  # by pid: a replacement takes over its predecessor's role
        self.results = self.ctx.Queue()
        self.stop_event = self.ctx.Event()
        self.go = self.ctx.Event()  # workers take tasks once it is set (start(held=False), or release())
        self.worker_ids: dict[int | None, str] = {}  # by pid (None only before a process starts)
        self.started = 0
        self.method = "spawn"  # how start() started the first workers (start_method)
        self.stopped = False

    def role_of(self, index: int) -> Role:
        """The role of the pool's `index`-th worker: the first R render, the others derive (module
        docstring)."""
        if not self.queues.split:
            return "all"
        return "render" if index < (self.render_workers or 0) else "derive"

    def _start_worker(self, method: str = "spawn", role: Role = "all") -> None:
        ctx: SpawnContext | ForkContext = self.ctx if method == "spawn" else mp.get_context("fork")
        conf = replace(self.conf, role=role)
        p = ctx.Process(target=worker_main, args=(conf, self.queues, self.results, self.stop_event, self.go),
                        name=f"omnidata-worker-{self.started}", daemon=False)
        p.start()
        self.started += 1
        self.worker_ids[p.pid] = f"{socket.gethostname()}:{p.pid}"
        self.roles[p.pid] = role
        self.procs.append(p)

    def start(self, *, held: bool = False) -> None:
        """Start the workers. Held workers only import (Python, numba kernels, Blender: ~2 CPU-s each) until
        release(): started before the job is validated and planned, that start-up overlaps the parent's
        work."""
        if not held:
            self.go.set()
        self.method = start_method(str(self.conf.settings.get("worker_start", "auto")))
        if self.method == "fork":
            if self.size > 1:
                for name in WORKER_MODULES:
                    importlib.import_module(name)
            # the children's collections then leave the inherited objects (and their pages) untouched
            gc.freeze()
        for i in range(self.size):
            self._start_worker(self.method, self.role_of(i))

    def release(self) -> None:
        """Let held workers take tasks."""
        self.go.set()

    def replace_dead(self) -> list[str]:
        """Start a new process for each one that exited; returns the worker ids of those that exited."""
        gone = []
        for p in list(self.procs):
            if not p.is_alive():
                p.join(0)
                self.procs.remove(p)
                gone.append(self.worker_ids.get(p.pid, f"{socket.gethostname()}:{p.pid}"))
                self._start_worker(role=self.roles.pop(p.pid, "all"))  # spawned: see the module docstring
        return gone

    def drain(self, timeout: float) -> list[WorkerMessage]:
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
        # held workers have nothing to finish: no grace (a refused input exits at once)
        if not self.go.is_set():
            grace = 0.0
        for q in self.queues.all():
            for _ in self.procs:
                try:
                    q.put_nowait(None)
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
        for q in (*self.queues.all(), self.results):
            q.cancel_join_thread()  # do not block exit on messages nobody will read
            q.close()
