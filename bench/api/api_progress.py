"""Benchmark: latency of GET /jobs/{id} (job progress) with 1M task rows, 50 concurrent clients, real uvicorn.

Builds a fresh Postgres database with one job of >= 1,000,000 tasks (views x the 19 default cues of an
unlabelled space incl. passes, a third of them done, counters maintained like the workers do), starts
`uvicorn services.api.app:app_from_env` in its own process, and measures with httpx (asyncio, one connection
per client):

- closed loop: 50 clients each sending the next request as soon as the previous answer arrives (saturation);
- paced: 50 clients each polling every `--interval` seconds (a dashboard-like load), the latency a user sees;
- the progress query alone (job row + counters, the database part of the request), sequentially.

Writes bench/results/api_progress.json. Run: .venv/bin/python bench/api/api_progress.py [--seconds 15]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import secrets
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from sqlalchemy import create_engine, func, select, text, update
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.api.jobs.rates import RateTracker
from services.api.jobs.service import detail_statement, fetch_job_detail
from services.core.db.bulk import bulk_insert
from services.core.db.counters import init_counts
from services.core.db.engine import make_engine, migrate
from services.core.db.models import Job, JobCounter, JobSpace, Space, Task, utcnow  # noqa: E402
from services.core.domain.cues import closure, default_cues  # noqa: E402
from services.core.settings import hash_token  # noqa: E402

RESULTS = results_dir()
REPO = Path(__file__).resolve().parents[2]
PG_ADMIN_URL = os.environ.get("OMNIDATA_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
TASKS = 1_000_000  # at least: views x (default cues of an unlabelled space + passes)


def percentiles(ms: list[float]) -> dict[str, float]:
    """p50/p90/p99/max/mean of latencies in milliseconds."""
    a = np.asarray(ms)
    return {
        "n": int(a.size),
        "p50_ms": round(float(np.percentile(a, 50)), 2),
        "p90_ms": round(float(np.percentile(a, 90)), 2),
        "p99_ms": round(float(np.percentile(a, 99)), 2),
        "max_ms": round(float(a.max()), 2),
        "mean_ms": round(float(a.mean()), 2),
    }


def create_database() -> str:
    """A new empty database; returns its URL."""
    name = f"omnidata_bench_{secrets.token_hex(4)}"
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    admin.dispose()
    return make_url(PG_ADMIN_URL).set(database=name).render_as_string(hide_password=False)


def drop_database(url: str) -> None:
    """Drop the benchmark database."""
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.execute(text(f'DROP DATABASE IF EXISTS "{make_url(url).database}" WITH (FORCE)'))
    admin.dispose()


def populate(url: str, owner: str, tasks: int = TASKS) -> tuple[int, int]:
    """One space and one running job with ~`tasks` tasks (a third done); returns (job id, task count)."""
    migrate(url)
    engine = make_engine(url)
    cues = closure(default_cues(False))
    views = -(-tasks // len(cues))
    with Session(engine) as s:
        space = Space(
            owner=owner, name="bench", source_key="spaces/1/bench.ply", source_format="ply", checksum="0" * 64
        )
        s.add(space)
        s.flush()
        job = Job(
            owner=owner, name="bench", spec={"cues": None}, state="running", started_at=utcnow(),
            output_root="jobs/1",
        )
        s.add(job)
        s.flush()
        s.add(JobSpace(job_id=job.id, space_id=space.id, position=0, cues=default_cues(False)))
        n = views * len(cues)
        i = np.arange(n)
        view = i // len(cues)
        bulk_insert(s, Task, {
            "job_id": np.full(n, job.id), "space_id": np.full(n, space.id), "point_idx": view // 3,
            "view_idx": view % 3, "cue": [cues[k % len(cues)] for k in range(n)],
        })
        init_counts(s, job.id, dict.fromkeys(cues, views))
        job.total_tasks = n
        s.commit()
        # a third of the tasks done: counters moved as services.core.db.states.transition would
        s.execute(
            update(Task).where(Task.job_id == job.id, Task.id % 3 == 0)
            .values(state="done", duration_s=0.5, finished_at=utcnow())
        )
        per_cue: dict[str, int] = {
            str(cue): int(k)
            for cue, k in s.execute(
                select(Task.cue, func.count())
                .where(Task.job_id == job.id, Task.state == "done")
                .group_by(Task.cue)
            )
        }
        for cue, k in per_cue.items():
            s.execute(update(JobCounter).where(JobCounter.job_id == job.id, JobCounter.cue == cue,
                                               JobCounter.state == "pending").values(n=JobCounter.n - k))
            s.add(JobCounter(job_id=job.id, cue=cue, state="done", n=k))
        s.commit()
        s.execute(text("ANALYZE"))
        s.commit()
        count = s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job.id)) or 0
        job_id = job.id
    engine.dispose()
    return job_id, int(count)


def query_latency(url: str, job_id: int, owner: str, n: int = 2000) -> dict[str, Any]:
    """The progress query alone, sequentially: the one statement GET /jobs/{id} runs (job row + counters +
    spaces as json aggregates), and the whole service call that also computes progress and serialises it."""
    engine = make_engine(url).execution_options(isolation_level="AUTOCOMMIT")  # as the API's read sessions
    rates = RateTracker()
    sql_ms, service_ms = [], []
    with Session(engine) as s:
        stmt = detail_statement("postgresql")
        for _ in range(n):
            t0 = time.perf_counter()
            s.execute(stmt, {"job_id": job_id, "owner": owner}).first()
            sql_ms.append((time.perf_counter() - t0) * 1000)
        for _ in range(n):
            t0 = time.perf_counter()
            fetch_job_detail(s, owner=owner, job_id=job_id, rates=rates).model_dump_json()
            service_ms.append((time.perf_counter() - t0) * 1000)
    engine.dispose()
    return {"statement": percentiles(sql_ms), "service_call": percentiles(service_ms)}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(url: str, token: str, owner: str, workers: int) -> tuple[subprocess.Popen[bytes], str]:
    """uvicorn in its own process (its own GIL), like `omnidata serve`."""
    port = free_port()
    env = dict(os.environ)
    env.update({
        "OMNIDATA_DATABASE_URL": url,
        "OMNIDATA_STORAGE_URL": Path(tempfile.mkdtemp(prefix="omnidata-bench-store-")).as_uri(),
        "OMNIDATA_API_TOKENS": json.dumps({hash_token(token): owner}),
    })
    proc = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "services.api.app:app_from_env", "--factory", "--host", "127.0.0.1",
         "--port", str(port), "--workers", str(workers), "--log-level", "warning", "--no-access-log"],
        cwd=REPO, env=env,
    )
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{base}/health", timeout=1).status_code == 200:
                return proc, base
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("uvicorn did not start")


async def load(
    base: str, token: str, job_id: int, n_tasks: int, *, clients: int, seconds: float, interval: float | None
) -> dict[str, Any]:
    """`clients` concurrent pollers for `seconds`; interval None = closed loop. Returns latencies."""
    headers = {"Authorization": f"Bearer {token}"}
    ms: list[float] = []
    errors = 0
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=base, headers=headers, limits=limits, timeout=30) as client:
        for _ in range(3):  # warm up connections and the server
            await client.get(f"/jobs/{job_id}")
        stop = time.monotonic() + seconds

        async def one(k: int) -> None:
            nonlocal errors
            if interval:
                await asyncio.sleep(interval * k / clients)  # spread the pollers evenly
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                r = await client.get(f"/jobs/{job_id}")
                dt = (time.perf_counter() - t0) * 1000
                if r.status_code != 200 or r.json()["progress"]["total"] != n_tasks:
                    errors += 1
                ms.append(dt)
                if interval:
                    await asyncio.sleep(max(0.0, interval - dt / 1000))

        t0 = time.monotonic()
        await asyncio.gather(*(one(k) for k in range(clients)))
        wall = time.monotonic() - t0
    out: dict[str, Any] = {"clients": clients, "seconds": round(wall, 1), "errors": errors,
                           "requests_per_s": round(len(ms) / wall, 1), **percentiles(ms)}
    if interval:
        out["interval_s"] = interval
    return out


def machine_load() -> list[float]:
    """1/5/15-minute load averages: the machine is shared, so results say how busy it was."""
    return [round(x, 2) for x in os.getloadavg()]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--interval", type=float, default=0.5, help="seconds between a paced client's polls")
    parser.add_argument(
        "--workers", default="1,2", help="uvicorn worker processes, comma-separated configurations"
    )
    parser.add_argument("--keep", action="store_true", help="keep the benchmark database")
    parser.add_argument("--tasks", type=int, default=TASKS, help="task rows of the job (fewer: a smoke run)")
    args = parser.parse_args()
    worker_counts = [int(w) for w in args.workers.split(",")]

    owner, token = "bench", secrets.token_urlsafe(24)
    url = create_database()
    runs: dict[str, Any] = {}
    try:
        t0 = time.perf_counter()
        job_id, n_tasks = populate(url, owner, args.tasks)
        populate_s = time.perf_counter() - t0
        print(f"populated {n_tasks} tasks in {populate_s:.1f} s", flush=True)
        load_before = machine_load()
        db = query_latency(url, job_id, owner)
        print(f"progress query alone: {db}", flush=True)
        for workers in worker_counts:
            proc, base = start_server(url, token, owner, workers)
            try:
                paced = asyncio.run(
                    load(
                        base, token, job_id, n_tasks, clients=args.clients, seconds=args.seconds,
                        interval=args.interval,
                    )
                )
                print(f"{workers} worker(s), paced ({args.interval} s polls): {paced}", flush=True)
                closed = asyncio.run(
                    load(
                        base, token, job_id, n_tasks, clients=args.clients, seconds=args.seconds,
                        interval=None,
                    )
                )
                print(f"{workers} worker(s), closed loop: {closed}", flush=True)
            finally:
                proc.terminate()
                proc.wait(timeout=30)
            runs[f"uvicorn_workers_{workers}"] = {"paced_clients": paced, "closed_loop_clients": closed}
    finally:
        if not args.keep:
            drop_database(url)
    best = min(runs.values(), key=lambda r: r["paced_clients"]["p99_ms"])
    result = {
        "benchmark": "api_progress",
        "what": "GET /jobs/{id} (progress from JobCounter rows) on a job with >= 1M task rows, httpx clients "
        "against uvicorn (separate process) on Postgres; client, server and Postgres share the CPUs",
        "tasks": n_tasks,
        "clients": args.clients,
        "p99_ms": best["paced_clients"]["p99_ms"],
        "p99_ms_meaning": f"best paced run: {args.clients} clients each polling every {args.interval} s",
        "progress_query_db_only": db,
        "runs": runs,
        "target": "progress query < 20 ms p99 on a 1M-task job (DESIGN.md section 7)",
        "note": "closed-loop latency ~= clients / throughput (queueing): it measures saturation, not a "
        "poll's cost",
        "load_average_before": load_before,
        "load_average_after": machine_load(),
        "populate_s": round(populate_s, 1),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "api_progress.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
