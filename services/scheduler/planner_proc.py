"""Planning off the dispatch loop: each claimed job is planned in a child process that the loop only watches.

A big plan takes seconds to minutes of CPU and grows with its views; done inside the loop it stopped every
other tenant's dispatch meanwhile and grew the scheduler itself. Here the loop claims a job, starts a child
(forked from a fork server, so it shares no connection or thread with the loop) that plans and persists it in
its own transaction under an address-space limit of `OMNIDATA_PLAN_MEMORY_MB`, and goes on dispatching. Each
tick it

- ends the child of a job that is no longer planning under this scheduler (cancelled, or re-taken): cancel
  stops the planning within a tick, and the child's final check would drop its plan anyway;
- extends the job's planner lease by the heartbeat timeout, a third of the way in: a scheduler killed while
  planning stops extending it, so another scheduler re-takes the job after the heartbeat timeout, the same
  "declared dead, then re-taken" rule as for workers (each child watches its scheduler and exits with it,
  and the fork server exits once neither holds its liveness pipe);
- records a child that died without a result (killed by the memory limit, crashed) as a failed attempt;
- makes room for a tenant with nothing planning when every slot is busy: a plan of the tenant holding the most
  slots (two or more) is paused (SIGSTOP, never inside one of its transactions: it holds no row lock while
  paused) and goes on where it was (SIGCONT) once no such tenant waits and a slot is free. A plan that takes
  minutes thus yields its slot, and a small job of another tenant is planned within a tick or two. Paused
  plans keep their memory, so at most `max_children` are paused at once; their time paused does not count
  against the planning time budget. A paused child still dies with its scheduler (its parent-death signal,
  SIGKILL, ends a stopped process too).
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import resource
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from multiprocessing.process import BaseProcess
from multiprocessing.sharedctypes import Synchronized
from pathlib import Path

from sqlalchemy import event, select, update
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.models import Job, JobState, utcnow
from services.core.settings import Settings
from services.core.temp_dirs import PLANNER_KINDS, sweep_orphans
from services.scheduler.persist import drop_cancelled_plan
from services.scheduler.plan_failure import PlanningError, record_planning_failure

log = logging.getLogger(__name__)

PR_SET_PDEATHSIG = 1
WATCHDOG_S = 0.5  # how often a planner checks that its scheduler is alive
# A child's entry point: (job_id, scheduler_id, settings, scheduler_pid, connections counter) -> None.
PlanTarget = Callable[[int, str, Settings, int, Synchronized], None]
PRELOAD = (
    "services.scheduler.loop", "services.scheduler.planning", "services.core.ingest.loading",
    "services.core.db.engine",
)


@dataclass
class PlannerChild:
    """A planner process: its job and tenant, when its job's lease was last extended and when it started
    (monotonic seconds), whether it is paused and for how long it was, and how many connections it holds
    (a counter shared with it)."""

    job_id: int
    owner: str
    process: BaseProcess
    extended: float
    started: float
    in_db: Synchronized
    paused_at: float | None = None
    paused_s: float = 0.0

    def active_s(self, now: float) -> float:
        """Seconds it has planned (paused time left out)."""
        paused_now = now - self.paused_at if self.paused_at is not None else 0.0
        return now - self.started - self.paused_s - paused_now


def plan_to_pause(running: list[PlannerChild]) -> PlannerChild | None:
    """Which running plan yields its slot to a tenant with nothing planning: the newest of the tenant
    holding the most slots, if it holds two or more (a tenant's only plan is never paused)."""
    by_owner: dict[str, list[PlannerChild]] = {}
    for child in running:
        by_owner.setdefault(child.owner, []).append(child)
    most = max(by_owner.values(), key=len, default=[])
    return max(most, key=lambda c: c.started) if len(most) >= 2 else None


class PlannerProcesses:
    """At most `max_children` (OMNIDATA_PLAN_PROCESSES) planner processes of one scheduler, watched from its
    loop."""

    def __init__(
        self, sm: sessionmaker[Session], settings: Settings, scheduler_id: str, target: PlanTarget, *,
        max_children: int | None = None,
    ) -> None:
        self.sessionmaker = sm
        self.target = target  # the child's entry point, given by the scheduler that plans the job
        self.settings = settings
        self.scheduler_id = scheduler_id
        self.max_children = max_children or settings.plan_processes
        self.lease_s = float(settings.heartbeat_timeout_s)
        self.children: dict[int, PlannerChild] = {}
        # A fork server: started once (a fresh interpreter, nothing shared with this loop's threads and
        # connections), it imports the planning stack up front and forks each planner from there in
        # milliseconds.
        self._ctx = mp.get_context("forkserver")
        self._ctx.set_forkserver_preload(list(PRELOAD))
        self.sweep()

    @property
    def running(self) -> list[PlannerChild]:
        """Children planning now (not paused)."""
        return [c for c in self.children.values() if c.paused_at is None]

    @property
    def paused(self) -> list[PlannerChild]:
        """Children paused for another tenant, longest paused first."""
        return sorted((c for c in self.children.values() if c.paused_at is not None),
                      key=lambda c: c.paused_at or 0.0)

    @property
    def free(self) -> int:
        """How many more jobs may be planned now (a paused plan holds no slot)."""
        return self.max_children - len(self.running)

    def start(self, job_id: int, owner: str) -> None:
        """Plan a job this scheduler has claimed (and committed) in a new child process (once per job)."""
        if job_id in self.children:  # re-claimed by this same scheduler: its planner is still at work
            return
        in_db = self._ctx.Value("i", 0)
        proc = self._ctx.Process(
            target=self.target, args=(job_id, self.scheduler_id, self.settings, os.getpid(), in_db),
            name=f"planner-{job_id}", daemon=True,
        )
        # the first start also starts the fork server: seconds, so the lease starts over after it
        proc.start()
        self._extend(job_id)
        self.children[job_id] = PlannerChild(job_id, owner, proc, time.monotonic(), time.monotonic(), in_db)
        log.info("job %d: planning in process %s", job_id, proc.pid)

    def make_room(self, tenant_waits: bool) -> None:
        """With a tenant that has nothing planning waiting and no slot free, pause one plan of a tenant
        holding several; with none waiting, resume paused plans into the free slots."""
        if tenant_waits:
            if self.free <= 0 and len(self.paused) < self.max_children:
                victim = plan_to_pause(self.running)
                if victim is not None and self._pause(victim):
                    log.info("job %d: planning paused, its slot goes to a tenant with nothing planning",
                             victim.job_id)
            return
        for child in self.paused[: max(0, self.free)]:
            os.kill(child.process.pid, signal.SIGCONT)  # type: ignore[arg-type]
            now = time.monotonic()
            child.paused_s += now - (child.paused_at or now)
            child.paused_at = None
            log.info("job %d: planning resumed", child.job_id)

    def _pause(self, child: PlannerChild) -> bool:
        """Stop a planner between its transactions (it holds no connection): False if it is in one now."""
        lock = child.in_db.get_lock()
        if not lock.acquire(timeout=0.05):
            return False
        try:
            pid = child.process.pid
            if child.in_db.value or pid is None or not child.process.is_alive():
                return False
            os.kill(pid, signal.SIGSTOP)
            # the counter's lock is held until it has stopped: it cannot stop holding it (or a connection)
            if not _wait_stopped(pid):
                os.kill(pid, signal.SIGCONT)
                return False
        finally:
            lock.release()
        child.paused_at = time.monotonic()
        return True

    def watch(self) -> list[int]:
        """One look at every child: end those whose job is gone, extend leases, reap the exited; returns the
        ids of jobs whose planning ended (planned, failed or dropped)."""
        if not self.children:
            return []
        ended = []
        ours = self._still_ours(list(self.children))
        for job_id, child in list(self.children.items()):
            if not child.process.is_alive():
                child.process.join()
                del self.children[job_id]
                ended.append(job_id)
                if child.process.exitcode != 0:
                    self._swept(child)
                    if job_id in ours:
                        self._died(job_id, child.process.exitcode)
            elif job_id not in ours:
                log.info("job %d is no longer planning under this scheduler; stopping its planner", job_id)
                self._kill(child)
                del self.children[job_id]
                ended.append(job_id)
                drop_cancelled_plan(self.sessionmaker, job_id)
            elif child.active_s(time.monotonic()) > self.settings.plan_timeout_s:
                self._kill(child)
                del self.children[job_id]
                ended.append(job_id)
                self._failed(job_id, PlanningError(
                    f"planning took longer than its time budget of {self.settings.plan_timeout_s} s "
                    "(OMNIDATA_PLAN_TIMEOUT_S): lower points.count or points.max_views, or split the job"))
            elif time.monotonic() - child.extended >= self.lease_s / 3.0:
                self._extend(job_id)
                child.extended = time.monotonic()
        return ended

    @staticmethod
    def sweep() -> None:
        """Remove the temporary folders of dead planners on this host (an earlier scheduler's, killed)."""
        sweep_orphans(PLANNER_KINDS)

    def stop_all(self) -> None:
        """Kill every child (the scheduler stops; the jobs are re-taken after their lease)."""
        for child in self.children.values():
            self._kill(child)
        self.children.clear()

    def _kill(self, child: PlannerChild) -> None:
        child.process.kill()
        child.process.join(10)
        self._swept(child)

    @staticmethod
    def _swept(child: PlannerChild) -> None:
        """Remove the temporary folders of a planner that was killed (or crashed) before its own cleanup."""
        if child.process.pid is not None and not child.process.is_alive():
            sweep_orphans(PLANNER_KINDS, only_pid=child.process.pid)

    def _still_ours(self, job_ids: list[int]) -> set[int]:
        with self.sessionmaker() as s:
            return {int(i) for i in s.scalars(select(Job.id).where(
                Job.id.in_(job_ids), Job.state == JobState.PLANNING, Job.planner == self.scheduler_id))}

    def _extend(self, job_id: int) -> None:
        with self.sessionmaker() as s:
            s.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == JobState.PLANNING, Job.planner == self.scheduler_id)
                .values(planner_lease_until=utcnow() + timedelta(seconds=self.lease_s))
                .execution_options(synchronize_session=False)
            )
            s.commit()

    def _died(self, job_id: int, exitcode: int | None) -> None:
        why = (
            f"killed by signal {-exitcode}"
            if exitcode is not None and exitcode < 0
            else f"exit code {exitcode}"
        )
        self._failed(job_id, PlannerDied(
            f"the planner process died ({why}); planning is limited to OMNIDATA_PLAN_MEMORY_MB="
            f"{self.settings.plan_memory_mb}"))

    def _failed(self, job_id: int, exc: BaseException) -> None:
        record_planning_failure(self.sessionmaker, job_id, self.scheduler_id, exc)


def _wait_stopped(pid: int, timeout_s: float = 1.0) -> bool:
    """Whether the process is stopped (state T in /proc) within `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            return False
        if stat[stat.rindex(")") + 2] in "Tt":
            return True
        time.sleep(0.001)
    return False


def count_connections(engine: Engine, in_db: Synchronized) -> None:
    """Keep `in_db` at the number of connections this process has checked out (paused only at 0)."""

    def add(delta: int) -> None:
        with in_db.get_lock():
            in_db.value += delta

    event.listen(engine, "checkout", lambda *_args: add(1))
    event.listen(engine, "checkin", lambda *_args: add(-1))


class PlannerDied(RuntimeError):
    """A planner process ended without recording a result (killed, crashed): the attempt is counted and
    retried."""


def die_with_scheduler(scheduler_pid: int) -> None:
    """End this process when the scheduler that started it is gone (kill -9 included).

    The fork server is this process's parent, and it lives as long as any process it forked holds its
    liveness pipe, so the parent-death signal alone would keep both alive: a watchdog thread checks the
    scheduler itself. (PR_SET_PDEATHSIG still covers the fork server dying first.)
    """
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    # not Linux: the watchdog, the lease and the final ownership check still hold
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while True:
            try:
                os.kill(scheduler_pid, 0)
            except ProcessLookupError:
                os._exit(3)
            except PermissionError:  # alive, under another user (pid reused): keep watching
                pass
            time.sleep(WATCHDOG_S)

    threading.Thread(target=watch, name="scheduler-watchdog", daemon=True).start()


def limit_memory(memory_mb: int) -> None:
    """Cap this process's address space (allocations beyond it raise MemoryError instead of growing the
    host)."""
    limit = int(memory_mb) * 2**20
    _soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(
        resource.RLIMIT_AS, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard)
    )
