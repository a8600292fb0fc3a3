"""A job of the Omnidata starter dataset's order on one machine: 1M views x 18 cues (18M task rows).

Persists a synthetic plan of `--views` views (4 per point, 64 cameras) with the 18 cues of an unlabelled room
through the product's own bulk path (db.bulk_insert: COPY), in chunks of `--chunk-views` views within one
transaction, as the planner does; then measures what the service needs to keep running at that size:

- persist: rows/s, wall time, peak RSS of the persisting process and of its Postgres backend (VmHWM);
- size: heap bytes per task row and per index entry of every task index (pg_relation_size), database size, and
  the extrapolation to the starter dataset's 14.6M views (`--target-views`);
- dispatch: dispatch passes over the 18M-row table (NullTransport, window `--window`), the dispatched tasks
  finished between passes as a fleet would, pass time and tasks/s;
- progress: the API's job detail query (one statement over the sharded counters) p50/p99, and its plan.

Writes `big_job` into bench/results/big_job.json (other keys kept) and drops its database.
Run: .venv/bin/python bench/scale/big_job.py [--views 1000000] [--chunk-views 50000]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select, text

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.scale_cost import ROOM_CUES  # noqa: E402
from bench.scale.fanout import create_database, drop_database, labelled_space, percentiles  # noqa: E402
from services.core.db.bulk import bulk_insert  # noqa: E402
from services.core.db.counters import init_counts  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.jobs import create_job  # noqa: E402
from services.core.db.models import Job, Space, Task, View  # noqa: E402
from services.core.db.states import transition  # noqa: E402
from services.core.domain.cues import CATALOG  # noqa: E402
from services.core.domain.jobspec import JobSpec  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.scheduler.compile import task_cues  # noqa: E402
from services.scheduler.dispatch import dispatch_once  # noqa: E402
from services.scheduler.transport import NullTransport  # noqa: E402

RESULTS = results_dir()
VIEWS_PER_POINT = 4
STARTER_VIEWS = 14_600_000


def task_columns(job_id: int, space_id: int, p0: int, p1: int) -> dict[str, Any]:
    """Task columns of points [p0, p1), 4 views each, in compile_tasks' order (view by view, cues
    topological)."""
    order = task_cues(ROOM_CUES)
    per_view = [c for c in order if not CATALOG[c].per_point]
    points, views, cues = [], [], []
    for p in range(p0, p1):
        for v in range(VIEWS_PER_POINT):
            names = order if v == 0 else per_view
            points.extend([p] * len(names))
            views.extend([v] * len(names))
            cues.extend(names)
    n = len(cues)
    return {"job_id": np.full(n, job_id, np.int64), "space_id": np.full(n, space_id, np.int64),
            "point_idx": np.asarray(points, np.int32), "view_idx": np.asarray(views, np.int32), "cue": cues}


def view_columns(job_id: int, space_id: int, p0: int, p1: int) -> dict[str, Any]:
    """View rows of points [p0, p1): pose as 16 floats, fov/roll/obliqueness in radians."""
    n = (p1 - p0) * VIEWS_PER_POINT
    pose = [float(x) for x in np.eye(4).reshape(16)]
    return {
        "job_id": [job_id] * n, "space_id": [space_id] * n,
        "point_idx": np.repeat(np.arange(p0, p1), VIEWS_PER_POINT),
        "v": np.tile(np.arange(VIEWS_PER_POINT), p1 - p0), "camera_idx": np.arange(n) % 64, "fov": [1.35] * n,
        "roll": [0.0] * n, "resolution": [512] * n, "obliqueness": [0.3] * n, "world_to_camera": [pose] * n,
        "in_sight": [True] * n,
    }


def vm_hwm_kb(pid: int) -> int:
    """Peak resident set of a process in KiB (VmHWM), 0 when unreadable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def persist(sm: Any, job_id: int, space_id: int, n_views: int, chunk_views: int) -> dict[str, Any]:
    """Every view and task row of the job in one transaction, chunk by chunk; counters; returns the
    figures."""
    n_points = n_views // VIEWS_PER_POINT
    chunk_points = max(1, chunk_views // VIEWS_PER_POINT)
    totals: dict[str, int] = {}
    t0 = time.perf_counter()
    with sm() as s:
        backend = int(s.scalar(text("SELECT pg_backend_pid()")))
        rows = 0
        for p0 in range(0, n_points, chunk_points):
            p1 = min(n_points, p0 + chunk_points)
            bulk_insert(s, View, view_columns(job_id, space_id, p0, p1))
            cols = task_columns(job_id, space_id, p0, p1)
            rows += bulk_insert(s, Task, cols)
            for cue, k in zip(*np.unique(np.asarray(cols["cue"]), return_counts=True), strict=True):
                totals[str(cue)] = totals.get(str(cue), 0) + int(k)
            if p0 // chunk_points % 5 == 0:
                print(f"  {rows:,} task rows in {time.perf_counter() - t0:.0f} s", flush=True)
        init_counts(s, job_id, totals)
        job = s.get(Job, job_id)
        assert job is not None
        job.state, job.total_tasks = "running", rows
        s.commit()
        backend_hwm = vm_hwm_kb(backend)
    wall = time.perf_counter() - t0
    return {
        "views": n_views, "task_rows": rows, "wall_s": round(wall, 1), "task_rows_per_s": round(rows / wall),
        "chunk_views": chunk_views,
        "peak_rss_mb": {
            "persisting_process": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "postgres_backend": round(backend_hwm / 1024, 1),
        },
    }


def sizes(sm: Any, rows: int, views: int) -> dict[str, Any]:
    """Bytes of the task heap and of each task index per row, database size, and the starter-size
    extrapolation."""
    with sm() as s:
        s.execute(text("ANALYZE task"))
        heap = int(s.scalar(text("SELECT pg_relation_size('task')")) or 0)
        toast = int(s.scalar(text("SELECT pg_total_relation_size('task') - pg_relation_size('task') "
                                  "- pg_indexes_size('task')")) or 0)
        idx = {
            str(n): int(b)
            for n, b in s.execute(
                text(
                    "SELECT indexrelname, pg_relation_size(indexrelid) FROM pg_stat_user_indexes WHERE "
                    "relname = 'task'"
                )
            )
        }
        view_bytes = int(s.scalar(text("SELECT pg_total_relation_size('view')")) or 0)
        db = int(s.scalar(text("SELECT pg_database_size(current_database())")) or 0)
        s.commit()
    per_row = (heap + toast + sum(idx.values())) / rows
    tasks_per_view = rows / views
    target_rows = STARTER_VIEWS * tasks_per_view
    return {
        "task_heap_bytes_per_row": round(heap / rows, 1),
        "task_index_bytes_per_row": {k: round(v / rows, 1) for k, v in sorted(idx.items())},
        "task_total_bytes_per_row": round(per_row, 1),
        "view_bytes_per_view": round(view_bytes / views, 1),
        "database_gb": round(db / 1e9, 2),
        "starter_dataset_extrapolation": {
            "views": STARTER_VIEWS, "task_rows": round(target_rows),
            "task_table_gb": round(target_rows * per_row / 1e9, 1),
            "view_table_gb": round(STARTER_VIEWS * view_bytes / views / 1e9, 1),
        },
    }


def finish_all(sm: Any, db_url: str, job_id: int, rows: int, views: int) -> dict[str, Any]:
    """Every task of the job done, as a finished job leaves them (output key, size, sha256, times), then
    VACUUM FULL: the footprint a finished job keeps (the pending-only dispatch index holds nothing of it)."""
    t0 = time.perf_counter()
    with sm() as s:
        s.execute(text(
            "UPDATE task SET state = 'done', worker_id = 'w-' || (id % 1000), attempts = 1, "
            "output_key = 'big/' || cue || '/point_' || point_idx || '_view_' || view_idx || '.png', "
            "size = 40000 + id % 1000, sha256 = md5(id::text) || md5(cue), duration_s = 0.05, "
            "queued_at = now(), started_at = now(), finished_at = now() WHERE job_id = :j"), {"j": job_id})
        s.execute(text("DELETE FROM job_counter WHERE job_id = :j"), {"j": job_id})
        s.commit()
    vacuum = make_engine(db_url, isolation_level="AUTOCOMMIT")
    with vacuum.connect() as c:
        c.execute(text("VACUUM FULL task"))  # compacted: what the finished rows take, without update bloat
    vacuum.dispose()
    return {"finish_s": round(time.perf_counter() - t0, 1), **sizes(sm, rows, views)}


def dispatch_passes(sm: Any, job_id: int, window: int, passes: int) -> dict[str, Any]:
    """`passes` dispatch passes over the big table; what each sent is finished (queued -> running -> done)
    after."""
    transport = NullTransport()
    times: list[float] = []
    t_all = time.perf_counter()
    for _ in range(passes):
        with sm() as s:
            t = time.perf_counter()
            dispatch_once(s, transport, window=window)
            times.append(time.perf_counter() - t)
        with sm() as s:
            ids = [
                i for (i,) in s.execute(select(Task.id).where(Task.job_id == job_id, Task.state == "queued"))
            ]
            transition(s, job_id=job_id, task_ids=ids, from_state="queued", to_state="running")
            transition(s, job_id=job_id, task_ids=ids, from_state="running", to_state="done")
            s.commit()
    sent = len(transport.sent)
    with sm() as s:  # the scheduler's safety net, every THOROUGH_DISPATCH_S: no counter-based scan bounds
        t = time.perf_counter()
        res = dispatch_once(s, NullTransport(), window=window, thorough=True)
        thorough_ms = 1000 * (time.perf_counter() - t)
    return {
        "window": window, "passes": passes, "tasks_sent": sent, "pass_ms": percentiles(times),
        "tasks_per_s_dispatch_only": round(sent / sum(times)),
        "wall_s": round(time.perf_counter() - t_all, 1), "thorough_pass_ms": round(thorough_ms),
        "thorough_pass_sent": res.sent,
    }


def progress(sm: Any, job_id: int, polls: int) -> dict[str, Any]:
    """The API's job detail query (counters summed over shards) polled `polls` times, and its server-side
    plan."""
    from services.api.jobs.service import fetch_job_detail

    lat = []
    with sm() as s:
        for _ in range(polls):
            t = time.perf_counter()
            fetch_job_detail(s, owner="bench", job_id=job_id, rates=None)
            s.rollback()
            lat.append(time.perf_counter() - t)
        counter_rows = int(
            s.scalar(text("SELECT count(*) FROM job_counter WHERE job_id = :j"), {"j": job_id}) or 0
        )
        plan = s.execute(text(
            "EXPLAIN (ANALYZE, FORMAT JSON) SELECT cue, state, sum(n) FROM job_counter WHERE job_id = :j "
            "GROUP BY cue, state HAVING sum(n) <> 0"), {"j": job_id}).scalar()
        s.rollback()
    doc = plan[0] if isinstance(plan, list) else json.loads(plan)[0]
    return {"detail_query": percentiles(lat), "counter_rows": counter_rows,
            "counters_sum_execution_ms": doc.get("Execution Time")}


def main(argv: list[str] | None = None) -> int:
    """Persist, measure, dispatch, poll; write big_job into big_job.json; drop the database."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, default=1_000_000)
    p.add_argument("--chunk-views", type=int, default=50_000)
    p.add_argument("--window", type=int, default=2_000, help="dispatch window (2 x 1000 workers)")
    p.add_argument("--passes", type=int, default=20)
    p.add_argument(
        "--finish-all", action="store_true",
        help="then finish every task and measure the footprint of the finished job (size_finished)",
    )
    p.add_argument("--key", default="big_job", help="the key of big_job.json the figures go to")
    p.add_argument("--out", type=Path, default=RESULTS / "big_job.json")
    args = p.parse_args(argv)
    db_url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="omnidata-big-job-"))
    try:
        migrate(db_url)
        engine = make_engine(db_url, pool_size=2)
        sm = make_sessionmaker(engine)
        store = LocalStore(tmp / "objects")
        space_id = labelled_space(sm, store, "big")
        with sm() as s:
            job = create_job(
                s, owner="bench", spec=JobSpec(cues=ROOM_CUES, name="big"), spaces=[s.get(Space, space_id)]
            )
            s.commit()
            job_id = job.id
        doc: dict[str, Any] = {"cues": len(ROOM_CUES), "load_avg_1m_start": round(os.getloadavg()[0], 2)}
        doc["persist"] = persist(sm, job_id, space_id, args.views, args.chunk_views)
        print(json.dumps(doc["persist"]), flush=True)
        doc["size"] = sizes(sm, doc["persist"]["task_rows"], args.views)
        print(json.dumps(doc["size"]), flush=True)
        doc["progress"] = progress(sm, job_id, 200)
        doc["dispatch"] = dispatch_passes(sm, job_id, args.window, args.passes)
        print(json.dumps(doc["dispatch"]), flush=True)
        doc["progress_after_dispatch"] = progress(sm, job_id, 200)
        if args.finish_all:
            doc["size_finished"] = finish_all(sm, db_url, job_id, doc["persist"]["task_rows"], args.views)
            print(json.dumps(doc["size_finished"]), flush=True)
        doc["peak_rss_mb_bench_process"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
        doc["load_avg_1m_end"] = round(os.getloadavg()[0], 2)
        engine.dispose()
    finally:
        drop_database(db_url)
    out = json.loads(args.out.read_text()) if args.out.exists() else {"benchmark": "big_job"}
    out[args.key] = {**doc, "views_arg": args.views}
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
