"""A small job of tenant B behind a big one of tenant A (issue 19 section 3): how much longer than its own work it takes.

The real deployment on this machine: Postgres, Redis, a local folder store, `omnidata scheduler` and one
`omnidata worker --render-threads 1` (as the README runs them). Tenant A submits a ~600-task job (object mode
on the bunny, rgb at 32 px: one render and one rgb task per view), at priority 9; once A is in its stride (20
tasks done), tenant B submits a 4-task job (2 views) at priority 0. Figures: B's latency (job created to done),
B's own work (the sum of its tasks' durations), the difference, and how many of A's tasks ran meanwhile.
A is then cancelled (the run stays under a few minutes).

Writes bench/results/fairness.json. Run: .venv/bin/python bench/fairness.py  (about 2 minutes)
"""

from __future__ import annotations

import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import redis
from sqlalchemy import func, select

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.fanout import create_database, drop_database  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.models import Job, Task  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BUNNY = REPO.parent / "shared" / "scenes" / "stanford_bunny" / "bun_zipper_res2.ply"
OUT = REPO / "bench" / "results" / "fairness.json"
REDIS_URL = os.environ.get("OMNIDATA_BENCH_REDIS_URL", "redis://127.0.0.1:6379/4")
BIG = "cameras: {mode: object, object_count: 40}\npoints: {count: 20, min_views: 2, max_views: 15}\n" \
      "views: {resolution: 32}\ncues: [rgb]\npriority: 9\nseed: 1\n"
SMALL = "cameras: {mode: object, object_count: 4}\npoints: {count: 1, min_views: 2, max_views: 2}\n" \
        "views: {resolution: 32}\ncues: [rgb]\npriority: 0\nseed: 2\n"


def start(env: dict[str, str], log: Path, *args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=REPO, env=env,
                            stdout=log.open("ab"), stderr=subprocess.STDOUT, start_new_session=True)


def submit(env: dict[str, str], owner: str, spec: str, tmp: Path) -> int:
    path = tmp / f"{owner}.yaml"
    path.write_text(spec)
    res = subprocess.run([sys.executable, "-m", "services.cli", "submit", str(BUNNY), "--spec", str(path), "--direct",
                          "--no-follow", "--owner", owner], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    return int(res.stdout.strip().splitlines()[-1])


def main() -> None:
    url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="bench-fairness-"))
    r = redis.Redis.from_url(REDIS_URL)
    r.flushdb()
    procs: list[subprocess.Popen[bytes]] = []
    try:
        migrate(url)
        engine = make_engine(url)
        sm = make_sessionmaker(engine)
        env = {k: v for k, v in os.environ.items() if not k.startswith("OMNIDATA_")}
        env.update(OMNIDATA_DATABASE_URL=url, OMNIDATA_BROKER_URL=REDIS_URL, OMNIDATA_STORAGE_URL=f"file://{tmp / 'store'}",
                   OMNIDATA_DATA_DIR=str(tmp / "data"), OMNIDATA_RENDER_DEVICE="cpu", PYTHONUNBUFFERED="1")
        procs.append(start(env, tmp / "scheduler.log", "scheduler", "--interval", "0.3"))
        procs.append(start(env, tmp / "worker.log", "worker", "--render-threads", "1", "--hostname", "bench-w@%h"))
        big = submit(env, "tenant-a", BIG, tmp)

        def done(job_id: int) -> int:
            with sm() as s:
                return int(s.scalar(select(func.count()).select_from(Task).where(
                    Task.job_id == job_id, Task.state == "done")) or 0)

        deadline = time.monotonic() + 240
        while done(big) < 20:
            assert time.monotonic() < deadline, (tmp / "scheduler.log").read_text()[-3000:]
            time.sleep(0.2)
        a_before = done(big)
        t_submit = time.monotonic()
        small = submit(env, "tenant-b", SMALL, tmp)
        while True:
            with sm() as s:
                state = s.get(Job, small).state  # type: ignore[union-attr]
            if state in ("done", "failed", "cancelled"):
                break
            assert time.monotonic() - t_submit < 180, "the small job did not finish"
            time.sleep(0.1)
        submit_s = time.monotonic() - t_submit
        a_meanwhile = done(big) - a_before
        with sm() as s:
            small_job = s.get(Job, small)
            big_job = s.get(Job, big)
            work = float(s.scalar(select(func.sum(Task.duration_s)).where(Task.job_id == small)) or 0.0)
            n_small = int(s.scalar(select(func.count()).select_from(Task).where(Task.job_id == small)) or 0)
            latency = (small_job.finished_at - small_job.created_at).total_seconds()  # type: ignore[union-attr,operator]
            result: dict[str, Any] = {
                "machine": f"{platform.node()} ({os.cpu_count()} cores, loaded by other developers' work)",
                "workers": 1, "big_job_tasks": int(big_job.total_tasks), "big_job_priority": 9,  # type: ignore[union-attr]
                "small_job_tasks": n_small, "small_job_priority": 0, "small_job_state": state,
                "small_latency_s": round(latency, 2), "small_own_work_s": round(work, 2),
                "small_latency_minus_work_s": round(latency - work, 2),
                "small_submit_to_planned_s": round(
                    (small_job.started_at - small_job.created_at).total_seconds(), 2),  # type: ignore[union-attr,operator]
                "big_tasks_done_meanwhile": a_meanwhile,
                "submit_cli_wall_s": round(submit_s, 2),  # `omnidata submit --direct` itself (start-up, registration)
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
    runs = json.loads(OUT.read_text()) if OUT.exists() else []
    OUT.write_text(json.dumps([*runs, result], indent=1) + "\n")


if __name__ == "__main__":
    main()
