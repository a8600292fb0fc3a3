"""Planning off the dispatch loop (issue 19 section 3): planner memory per view, and a 20M-view spec beside a
small job.

Real Postgres, a local folder store, the bunny in object mode, the real Scheduler with planner processes
(`plan_in_processes=True`, as `omnidata scheduler` runs it) and a NullTransport (what is dispatched is
counted).

1. per view: plans two object-mode specs of different sizes (all default cues) and samples the planner child's
   resident size (VmHWM from /proc); the slope is the planner's bytes per view (PLAN_BYTES_PER_VIEW is set
   above it).
2. the issue's 20M-view spec: refused up front by the default budget (the message is recorded); written to the
   database directly (past the API) it fails in the scheduler's planner before any planning, while tenant B's
   small job, submitted 1 s later, is planned and dispatched: the scheduler's RSS is sampled, every tick
   timed.
3. the same with a big plan within the budget (27k views, ~15 s of planning) that is cancelled after 9 s
   (while its rows are being written):
   B's plan and dispatch times, and the time from the cancel to the planner process gone.

4. chunked planning (BENCH_STREAM_ONLY=1, sizes in BENCH_STREAM_VIEWS, e.g. 500000,2000000): rgb-only
   object-mode plans with 100 cameras; the planner child's peak RSS (VmHWM) and CPU time per size: flat in the
   views when the plan is written in chunks (run it on an older checkout for the whole-plan figures).

Writes bench/results/planner.json. Run: .venv/bin/python bench/plan/planner.py  (about 2-4 minutes)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import add_run, results_dir  # noqa: E402
from bench.lib.smoke import SMOKE, SMOKE_HELP  # noqa: E402
from bench.scale.fanout import create_database, drop_database  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.jobs import cancel_job, create_job  # noqa: E402
from services.core.db.models import Job, Task  # noqa: E402
from services.core.domain.jobspec import JobSpec  # noqa: E402
from services.core.domain.plan_budget import PlanOverBudget, check_plan_budget  # noqa: E402
from services.core.ingest.registry import register_space  # noqa: E402
from services.core.settings import get_settings  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.scheduler.loop import Scheduler  # noqa: E402
from services.scheduler.transport import NullTransport  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
BUNNY = REPO.parent / "shared" / "scenes" / "stanford_bunny" / "bun_zipper_res2.ply"
OUT = results_dir() / "planner.json"
SPEC_20M = {"cameras": {"mode": "object", "object_count": 100},
            "points": {"count": 200000, "min_views": 2, "max_views": 100}}
SMALL = {
    "cameras": {"mode": "object", "object_count": 4}, "points": {"count": 1, "min_views": 2, "max_views": 2},
    "views": {"resolution": 32}, "cues": ["rgb"],
}
SIZES = [(40, 500), (40, 2000)]  # (cameras, points): 20k and 80k views, every default cue
if SMOKE:
    SIZES = [(4, 5), (4, 10)]
# chunked planning: rgb only (the task rows per view stay few), 100 cameras per point; sizes from the command
# line
STREAM_SIZES = [int(a) for a in os.environ.get("BENCH_STREAM_VIEWS", "100000,400000").split(",")]


def rss_mb(pid: int, field: str = "VmRSS") -> float:
    """A process's resident size (or its peak, VmHWM) in MB, 0 when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


class Sampler:
    """Samples this process's RSS and its planner children's peak RSS every 0.1 s in a thread."""

    def __init__(self, sched: Scheduler) -> None:
        self.sched = sched
        self.scheduler_peak = 0.0
        self.child_peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            self.scheduler_peak = max(self.scheduler_peak, rss_mb(os.getpid()))
            planners = self.sched.planners
            for child in list(planners.children.values()) if planners else []:
                if child.process.pid:
                    self.child_peak = max(self.child_peak, rss_mb(child.process.pid, "VmHWM"))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def new_job(sm: Any, store: LocalStore, owner: str, spec: dict[str, Any]) -> int:
    """A pending job of `owner` over the bunny (registered for that tenant on first use)."""
    from sqlalchemy import select

    from services.core.db.models import Space

    with sm() as s:
        space = s.scalars(select(Space).where(Space.owner == owner)).first()
        if space is None:
            space = register_space(s, store, owner=owner, name="bunny", source_path=BUNNY)
        job = create_job(s, owner=owner, spec=JobSpec.model_validate(spec), spaces=[space])
        s.commit()
        return int(job.id)


def job_state(sm: Any, job_id: int) -> tuple[str, str | None]:
    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None
        return job.state, job.error


def per_view(sm: Any, store: LocalStore, settings: Any) -> dict[str, Any]:
    """Planner child peak RSS and time for two plan sizes, and the slope per view."""
    rows = []
    for cams, points in SIZES:
        sched = Scheduler(
            sm, store, NullTransport(), settings, f"bench-size-{points}", plan_in_processes=True
        )
        spec = {"cameras": {"mode": "object", "object_count": cams},
                "points": {"count": points, "min_views": 2, "max_views": cams}}
        job_id = new_job(sm, store, "size", spec)
        sampler = Sampler(sched)
        t0 = time.monotonic()
        while job_state(sm, job_id)[0] in ("pending", "planning"):
            sched.plan_pending()
            time.sleep(0.1)
        sampler.stop()
        with sm() as s:
            views = int(s.get(Job, job_id).plan_summary["spaces"]["bunny"]["views"])  # type: ignore[union-attr]
            tasks = int(s.get(Job, job_id).total_tasks)  # type: ignore[union-attr]
        rows.append(
            {
                "views": views, "tasks": tasks, "state": job_state(sm, job_id)[0],
                "planner_peak_rss_mb": round(sampler.child_peak, 1),
                "planning_s": round(time.monotonic() - t0, 1),
            }
        )
        print("plan size:", rows[-1], flush=True)
    (a, b) = rows
    slope = (b["planner_peak_rss_mb"] - a["planner_peak_rss_mb"]) * 2**20 / max(1, b["views"] - a["views"])
    return {"sizes": rows, "bytes_per_view": round(slope)}


def child_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process (from /proc/<pid>/stat), 0 when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError):
        return 0.0


def streamed(sm: Any, store: LocalStore, settings: Any) -> dict[str, Any]:
    """The planner child's peak RSS (VmHWM) as the plan grows: rgb-only object-mode plans of STREAM_SIZES
    views."""
    rows = []
    for views in STREAM_SIZES:
        sched = Scheduler(
            sm, store, NullTransport(), settings, f"bench-stream-{views}", plan_in_processes=True
        )
        spec = {"cameras": {"mode": "object", "object_count": 100},
                "points": {"count": views // 34, "min_views": 2, "max_views": 100},
                "cues": ["rgb"]}
        job_id = new_job(sm, store, "stream", spec)
        sampler = Sampler(sched)
        t0, cpu = time.monotonic(), 0.0
        while job_state(sm, job_id)[0] in ("pending", "planning"):
            sched.plan_pending()
            for child in list(sched.planners.children.values()):  # type: ignore[union-attr]
                cpu = max(cpu, child_cpu_s(child.process.pid or 0))
            time.sleep(0.1)
        sampler.stop()
        with sm() as s:
            job = s.get(Job, job_id)
            assert job is not None
            planned = (
                job.plan_summary["spaces"]["bunny"] if job.plan_summary and job.state == "running" else {}
            )
        rows.append(
            {
                "views": planned.get("views"), "points": planned.get("points"), "tasks": job.total_tasks,
                "state": job.state, "error": job.error, "planner_peak_rss_mb": round(sampler.child_peak, 1),
                "planner_cpu_s": round(cpu, 1), "planning_wall_s": round(time.monotonic() - t0, 1),
                "load_avg_1m": round(os.getloadavg()[0], 2),
            }
        )
        print("streamed plan:", rows[-1], flush=True)
    return {"chunk_views": getattr(settings, "plan_chunk_views", None), "sizes": rows}


def big_beside_small(sm: Any, store: LocalStore, settings: Any, big_spec: dict[str, Any],
                     cancel_after_s: float) -> dict[str, Any]:
    """Tenant A's big job planning (cancelled after `cancel_after_s` if still planning) while tenant B's small
    job is planned and dispatched."""
    transport = NullTransport()
    sched = Scheduler(sm, store, transport, settings, "bench-big", plan_in_processes=True)
    big = new_job(sm, store, "tenant-a", big_spec)
    sampler = Sampler(sched)
    t0 = time.monotonic()
    ticks: list[float] = []
    small = None
    small_running = small_sent = cancelled_at = child_gone = None
    while time.monotonic() - t0 < 150:
        t = time.monotonic()
        sched.tick()
        ticks.append(time.monotonic() - t)
        now = time.monotonic() - t0
        if small is None and now > 1.0:
            small = new_job(sm, store, "tenant-b", SMALL)
        if small is not None and small_running is None and job_state(sm, small)[0] == "running":
            small_running = now
        if small is not None and small_sent is None and transport.sent:
            with sm() as s:
                ids = [i for i, _ in transport.sent]
                if s.query(Task.id).filter(Task.job_id == small, Task.id.in_(ids)).first():
                    small_sent = now
        state, _ = job_state(sm, big)
        if state == "planning" and cancelled_at is None and now > cancel_after_s:
            with sm() as s:
                cancel_job(s, s.get(Job, big))  # type: ignore[arg-type]
                s.commit()
            cancelled_at = now
        if (
            state != "planning"
            and cancelled_at is not None
            and child_gone is None
            and not sched.planners.children
        ):  # type: ignore[union-attr]
            child_gone = now
        if (
            state not in ("pending", "planning")
            and small_sent is not None
            and (cancelled_at is None or child_gone)
        ):
            break
        time.sleep(0.05)
    sampler.stop()
    state, error = job_state(sm, big)
    ticks.sort()
    return {
        "spec": big_spec, "plan_memory_mb": settings.plan_memory_mb, "big_job_end_state": state,
        "big_job_error": error, "scheduler_peak_rss_mb": round(sampler.scheduler_peak, 1),
        "planner_child_peak_rss_mb": round(sampler.child_peak, 1),
        "small_job_running_after_s": small_running and round(small_running - 1.0, 2),
        "small_job_first_dispatch_after_s": small_sent and round(small_sent - 1.0, 2),
        "tick_s": {"p50": round(ticks[len(ticks) // 2], 4), "max": round(ticks[-1], 4), "n": len(ticks)},
        "cancel_to_planner_gone_s": (
            round(child_gone - cancelled_at, 2) if cancelled_at and child_gone else None
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP + "; the plan sizes only")
    ap.parse_args()
    results: dict[str, Any] = {
        "machine": f"{platform.node()} ({os.cpu_count()} cores, loaded by other developers' work)"
    }
    try:
        check_plan_budget(JobSpec.model_validate(SPEC_20M), memory_mb=get_settings().plan_memory_mb)
        results["refused_up_front"] = None
    except PlanOverBudget as e:
        results["refused_up_front"] = str(e)
    url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="bench-planner-"))
    try:
        migrate(url)
        engine = make_engine(url)
        sm = make_sessionmaker(engine)
        store = LocalStore(tmp / "objects")
        settings = get_settings(
            database_url=url, storage_url=f"file://{tmp / 'objects'}", data_dir=tmp / "data",
            plan_memory_mb=16_384, heartbeat_timeout_s=30,
        )
        # only the chunked-planning figures (before/after comparisons)
        if os.environ.get("BENCH_STREAM_ONLY"):
            results["streamed"] = streamed(sm, store, settings.model_copy(update={"plan_timeout_s": 36000}))
            raise SystemExit(_save(results))
        results["per_view"] = per_view(sm, store, settings)
        if SMOKE:
            engine.dispose()
            raise SystemExit(_save(results))
        low = settings.model_copy(update={"plan_memory_mb": 1536})
        # the 20M spec written past the API: the scheduler refuses it before planning, B goes on
        results["spec_20m_beside_small"] = big_beside_small(sm, store, low, SPEC_20M, cancel_after_s=90)
        slow = {"cameras": {"mode": "object", "object_count": 40},
                "points": {"count": 2000, "min_views": 2, "max_views": 40}}
        # a big plan within the budget: B is planned and dispatched beside it; A is cancelled mid-planning
        results["slow_plan_beside_small"] = big_beside_small(sm, store, settings, slow, cancel_after_s=9)
        engine.dispose()
    finally:
        drop_database(url)
    _save(results)


def _save(results: dict[str, Any]) -> int:
    results["label"] = os.environ.get("BENCH_LABEL", "")
    print(json.dumps(results, indent=1))
    add_run(OUT, results)
    return 0


if __name__ == "__main__":
    main()
