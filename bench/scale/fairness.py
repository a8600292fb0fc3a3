"""Tenant B's small job behind tenant A's work: how much longer than its own work it takes.

The real deployment on this machine: Postgres, Redis, a local folder store, `omnidata scheduler` and one
`omnidata worker --render-threads 1` (as the README runs them). Two scenarios:

- `big_job` (issue 19 section 3): tenant A submits a ~600-task job (object mode on the bunny, rgb at 32
  px: one render and one rgb task per view), at priority 9; once A is in its stride (20 tasks done),
  tenant B submits a 4-task job (2 views) at priority 0.
- `slow_planning` (issue 51 section 2): tenant A submits two jobs whose planning takes minutes here
  (many points on the bunny: sampling, not rendering), which take both of the scheduler's planning slots
  (OMNIDATA_PLAN_PROCESSES=2); once both have planned for `--head-start` seconds, tenant B submits the
  same 4-task job.

Figures: B's latency (job created to done), B's own work (the sum of its tasks' durations), the difference,
when B was claimed for planning, and what A did meanwhile (tasks done; plans still under way). A is then
cancelled (the run stays within a few minutes). `--code DIR` runs the services from another checkout (the code
before a change), with the same benchmark.

Writes bench/results/fairness.json (one entry per run, appended).
Run: .venv/bin/python bench/scale/fairness.py [--scenario slow_planning] [--code /work/main]  (2-5 minutes)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import redis
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import add_run, results_dir  # noqa: E402
from bench.lib.smoke import SMOKE, SMOKE_HELP  # noqa: E402
from bench.scale.fanout import create_database, drop_database  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.models import Job, Task, utcnow  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
BUNNY = REPO.parent / "shared" / "scenes" / "stanford_bunny" / "bun_zipper_res2.ply"
OUT = results_dir() / "fairness.json"
REDIS_URL = os.environ.get("OMNIDATA_BENCH_REDIS_URL", "redis://127.0.0.1:6379/4")
BIG = "cameras: {mode: object, object_count: 40}\npoints: {count: 20, min_views: 2, max_views: 15}\n" \
      "views: {resolution: 32}\ncues: [rgb]\npriority: 9\nseed: 1\n"
# planning that takes minutes on this machine and little else: many points, two views each
SLOW_PLAN = (
    "cameras: {mode: object, object_count: 2000}\n"
    "points: {count: 12000, min_views: 2, max_views: 2}\nviews: {resolution: 32}\ncues: [rgb]\nseed: 3\n"
)
FINAL = ("done", "failed", "cancelled")
SMALL = "cameras: {mode: object, object_count: 4}\npoints: {count: 1, min_views: 2, max_views: 2}\n" \
        "views: {resolution: 32}\ncues: [rgb]\npriority: 0\nseed: 2\n"


def start(env: dict[str, str], log: Path, code: Path, *args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=code, env=env,
                            stdout=log.open("ab"), stderr=subprocess.STDOUT, start_new_session=True)


def submit(env: dict[str, str], owner: str, spec: str, tmp: Path, name: str | None = None) -> int:
    path = tmp / f"{name or owner}.yaml"
    path.write_text(spec)
    res = subprocess.run(
        [
            sys.executable, "-m", "services.cli", "submit", str(BUNNY), "--spec", str(path), "--direct",
            "--no-follow", "--owner", owner,
        ],
        cwd=REPO, env=env, capture_output=True, text=True, check=True,
    )
    return int(res.stdout.strip().splitlines()[-1])


class Bench:
    """The running deployment of one benchmark run and what it reads back."""

    def __init__(self, sm: sessionmaker[Session], env: dict[str, str], tmp: Path) -> None:
        self.sm, self.env, self.tmp = sm, env, tmp

    def done(self, job_id: int) -> int:
        with self.sm() as s:
            return int(s.scalar(select(func.count()).select_from(Task).where(
                Task.job_id == job_id, Task.state == "done")) or 0)

    def state(self, job_id: int) -> str:
        with self.sm() as s:
            return str(s.get(Job, job_id).state)  # type: ignore[union-attr]

    def wait(self, what: str, cond: Callable[[], bool], limit_s: float) -> bool:
        deadline = time.monotonic() + limit_s
        while not cond():
            if time.monotonic() > deadline:
                print(f"timed out waiting for {what}; scheduler log:\n"
                      + (self.tmp / "scheduler.log").read_text()[-3000:], file=sys.stderr)
                return False
            time.sleep(0.1)
        return True

    def small_figures(self, small: int, finished: bool) -> dict[str, Any]:
        """B's latency and own work (`finished`: it settled within the limit; else latency so far)."""
        with self.sm() as s:
            job = s.get(Job, small)
            assert job is not None
            work = float(s.scalar(select(func.sum(Task.duration_s)).where(Task.job_id == small)) or 0.0)
            n_small = int(s.scalar(select(func.count()).select_from(Task).where(Task.job_id == small)) or 0)
            end = job.finished_at if finished and job.finished_at else utcnow()
            latency = (end - job.created_at).total_seconds()
            claimed = (job.started_at - job.created_at).total_seconds() if job.started_at else None
            return {
                "small_job_tasks": n_small, "small_job_priority": 0, "small_job_state": str(job.state),
                "small_latency_s": round(latency, 2), "small_own_work_s": round(work, 2),
                "small_latency_minus_work_s": round(latency - work, 2),
                "small_submit_to_planned_s": round(claimed, 2) if claimed is not None else None,
                "small_finished_within_limit": finished,
            }


def big_job(bench: Bench) -> dict[str, Any]:
    big = submit(bench.env, "tenant-a", BIG, bench.tmp)
    stride = 2 if SMOKE else 20
    assert bench.wait(f"A's first {stride} tasks", lambda: bench.done(big) >= stride, 240)
    a_before = bench.done(big)
    t_submit = time.monotonic()
    small = submit(bench.env, "tenant-b", SMALL, bench.tmp)
    finished = bench.wait("B's job", lambda: bench.state(small) in FINAL, 180)
    submit_s = time.monotonic() - t_submit
    with bench.sm() as s:
        big_tasks = int(s.get(Job, big).total_tasks)  # type: ignore[union-attr]
    return {"workers": 1, "big_job_tasks": big_tasks, "big_job_priority": 9,
            **bench.small_figures(small, finished), "big_tasks_done_meanwhile": bench.done(big) - a_before,
            "submit_cli_wall_s": round(submit_s, 2)}  # `omnidata submit --direct` itself (start-up, ingest)


def slow_planning(bench: Bench, head_start_s: float, limit_s: float) -> dict[str, Any]:
    slow = [submit(bench.env, "tenant-a", SLOW_PLAN, bench.tmp, name=f"tenant-a-{i}") for i in range(2)]
    assert bench.wait("A's two plans", lambda: all(bench.state(j) == "planning" for j in slow), 120)
    time.sleep(head_start_s)
    assert all(bench.state(j) == "planning" for j in slow), "A's plans ended before B came: more points"
    small = submit(bench.env, "tenant-b", SMALL, bench.tmp)
    finished = bench.wait("B's job", lambda: bench.state(small) in FINAL, limit_s)
    return {"workers": 1, "plan_processes": 2, "slow_plan_spec": SLOW_PLAN.replace("\n", "; "),
            "slow_plans": len(slow), "slow_plans_head_start_s": head_start_s, "small_wait_limit_s": limit_s,
            **bench.small_figures(small, finished),
            "slow_plans_still_planning_when_small_settled": sum(bench.state(j) == "planning" for j in slow)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", choices=("big_job", "slow_planning"), default="big_job")
    ap.add_argument("--code", type=Path, default=REPO, help="checkout whose scheduler and worker run")
    ap.add_argument("--head-start", type=float, default=10.0, help="seconds A plans before B submits")
    ap.add_argument("--limit", type=float, default=300.0, help="longest wait for B's job (slow_planning)")
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP + "; B comes after A's first 2 tasks")
    args = ap.parse_args()
    url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="bench-fairness-"))
    r = redis.Redis.from_url(REDIS_URL)
    r.flushdb()
    procs: list[subprocess.Popen[bytes]] = []
    try:
        migrate(url)
        engine = make_engine(url)
        env = {k: v for k, v in os.environ.items() if not k.startswith("OMNIDATA_")}
        env.update(
            OMNIDATA_DATABASE_URL=url, OMNIDATA_BROKER_URL=REDIS_URL,
            OMNIDATA_STORAGE_URL=f"file://{tmp / 'store'}", OMNIDATA_DATA_DIR=str(tmp / "data"),
            OMNIDATA_RENDER_DEVICE="cpu", PYTHONUNBUFFERED="1", OMNIDATA_PLAN_PROCESSES="2",
        )
        service_env = {**env, "PYTHONPATH": str(args.code.resolve())}
        procs.append(start(service_env, tmp / "scheduler.log", args.code, "scheduler", "--interval", "0.3"))
        procs.append(start(service_env, tmp / "worker.log", args.code, "worker", "--render-threads", "1",
                           "--hostname", "bench-w@%h"))
        bench = Bench(make_sessionmaker(engine), env, tmp)
        figures = (big_job(bench) if args.scenario == "big_job"
                   else slow_planning(bench, args.head_start, args.limit))
        result: dict[str, Any] = {
            "machine": f"{platform.node()} ({os.cpu_count()} cores, loaded by other developers' work)",
            "scenario": args.scenario,
            "code": "this checkout" if args.code.resolve() == REPO else str(args.code),
            "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=args.code,
                                     capture_output=True, text=True).stdout.strip(),
            **figures,
        }
    finally:
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(30)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(p.pid, signal.SIGKILL)
        drop_database(url)
        r.flushdb()
    print(json.dumps(result, indent=1))
    add_run(OUT, result, default_scenario="big_job")


if __name__ == "__main__":
    main()
