"""Benchmark: 200k task rows through services.core.db.bulk.bulk_insert on a fresh Postgres database and on
SQLite.

Writes bench/results/bulk_insert.json. Times include the commit. Run: .venv/bin/python
bench/scale/bulk_insert.py
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import secrets
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, func, select, text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.core.db.bulk import bulk_insert
from services.core.db.engine import make_engine, migrate
from services.core.db.models import Job, Task  # noqa: E402

RESULTS = results_dir()
PG_ADMIN_URL = os.environ.get("OMNIDATA_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
CUES = ("rgb", "normal", "depth_zbuffer", "depth_euclidean", "mask_valid", "reshading", "edge_texture")


def task_columns(job_id: int, n: int) -> dict[str, object]:
    """n task rows as columns: 7 cues per view, 3 views per point, like a planner's output."""
    i = np.arange(n)
    return {
        "job_id": np.full(n, job_id),
        "space_id": np.full(n, 1),
        "point_idx": i // (3 * len(CUES)),
        "view_idx": (i // len(CUES)) % 3,
        "cue": [CUES[k % len(CUES)] for k in range(n)],
    }


def run_one(url: str, n: int) -> dict[str, float]:
    """Insert n tasks for a new job in one transaction; returns seconds and rows/s."""
    migrate(url)
    engine = make_engine(url)
    try:
        with Session(engine) as s:
            job = Job(owner="bench", name="bench", spec={})
            s.add(job)
            s.commit()
            cols = task_columns(job.id, n)
            t0 = time.perf_counter()
            inserted = bulk_insert(s, Task, cols)
            s.commit()
            dt = time.perf_counter() - t0
            count = s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job.id))
            assert inserted == n == count, (inserted, n, count)
    finally:
        engine.dispose()
    return {"rows": n, "seconds": round(dt, 3), "rows_per_s": round(n / dt)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rows", type=int, default=200_000)
    args = ap.parse_args()

    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    name = f"omnidata_bench_{os.getpid()}_{secrets.token_hex(3)}"
    with admin.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    pg_url = make_url(PG_ADMIN_URL).set(database=name).render_as_string(hide_password=False)
    try:
        pg = run_one(pg_url, args.rows)
    finally:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()
    with tempfile.TemporaryDirectory() as tmp:
        lite = run_one(f"sqlite:///{tmp}/bench.db", args.rows)

    result = {
        "benchmark": "bulk_insert",
        "what": "task rows inserted by services.core.db.bulk.bulk_insert in one transaction "
        "(commit included)",
        "postgres_copy": pg,
        "sqlite_executemany": lite,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bulk_insert.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"postgres COPY:       {pg['rows']} rows in {pg['seconds']} s = {pg['rows_per_s']:,} rows/s")
    print(f"sqlite executemany:  {lite['rows']} rows in {lite['seconds']} s = {lite['rows_per_s']:,} rows/s")
    print(f"wrote {RESULTS / 'bulk_insert.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
