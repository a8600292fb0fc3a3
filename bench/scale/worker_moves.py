"""CPU per view of the embedded worker's own database moves on SQLite (issue 20: the embedded default's cost
per view): claim the view's render task, claim the rest of the view with it, record the whole view done.

A fresh SQLite file (the embedded default's settings: WAL, synchronous NORMAL) holds one running job of
`--views` views of the default cues (the render queued, the rest pending, as after dispatch); one process
makes the three moves per view as a worker does (services.core.db.worker_moves) and times each with process
CPU time. Run: .venv/bin/python bench/scale/worker_moves.py [--views 200] [--label NAME]; writes
bench/results/worker_moves.json. With PYTHONPATH set to an older checkout it measures that code (its moves
lived in services.core.db.states).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path

from sqlalchemy import select

# appended, not prepended: an older checkout on PYTHONPATH keeps its services ahead of this one's
sys.path.append(str(Path(__file__).resolve().parents[2]))

from bench.lib.results import results_dir  # noqa: E402
from services.core.db.bulk import bulk_insert
from services.core.db.counters import add_counts, job_progress
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.db.models import Job, Task, utcnow
from services.core.domain.cues import closure, default_cues

try:
    from services.core.db import worker_moves as moves
except ImportError:  # an older checkout
    from services.core.db import states as moves  # type: ignore[no-redef]

RESULTS = results_dir() / "worker_moves.json"


def make_job(sm, cues: list[str], views: int) -> tuple[int, dict[tuple[int, str], int]]:
    with sm() as s:
        job = Job(owner="bench", name="moves", spec={}, state="running")
        s.add(job)
        s.flush()
        cols: dict[str, list[object]] = {
            k: [] for k in ("job_id", "space_id", "point_idx", "view_idx", "cue", "state")
        }
        deltas: dict[tuple[str, str], int] = {}
        for v in range(views):
            for cue in cues:
                state = "queued" if cue == "passes" else "pending"
                for k, x in zip(cols, (job.id, 1, v, 0, cue, state), strict=True):
                    cols[k].append(x)
                deltas[(cue, state)] = deltas.get((cue, state), 0) + 1
        bulk_insert(s, Task, cols)
        add_counts(s, job.id, deltas)
        s.commit()
        ids = {(int(p), str(c)): int(i) for i, p, c in s.execute(
            select(Task.id, Task.point_idx, Task.cue).where(Task.job_id == job.id))}
        return int(job.id), ids


def finish(s, job_id: int, results: list) -> set[int]:
    now = utcnow()
    try:
        return moves.finish_tasks(s, worker_id="w", results=results, now=now)
    except TypeError:  # an older signature took the job id
        return moves.finish_tasks(s, job_id=job_id, worker_id="w", results=results, now=now)


def run(views: int) -> dict[str, float]:
    cues = closure(default_cues(has_semantics=False))  # a scan's cues and `passes`; point_info in every view
    with tempfile.TemporaryDirectory() as d:
        url = f"sqlite:///{d}/bench.db"
        migrate(url)
        sm = make_sessionmaker(make_engine(url))
        job_id, ids = make_job(sm, cues, views)
        spent = {"claim": 0.0, "claim_view": 0.0, "record_done": 0.0}
        for v in range(views):
            now = utcnow()
            lease = now + timedelta(seconds=60)
            t0 = time.process_time()
            with sm() as s:
                assert moves.claim_task(
                    s, task_id=ids[(v, "passes")], worker_id="w", now=now, lease_until=lease
                )
            t1 = time.process_time()
            with sm() as s:
                rows = moves.claim_view_tasks(
                    s, task_id=ids[(v, "passes")], job_id=job_id, space_id=1, point=v, view=0, worker_id="w",
                    now=now, lease_until=lease, with_pending=True,
                )
            assert len(rows) == len(cues) - 1
            t2 = time.process_time()
            with sm() as s:
                done = finish(s, job_id, [(ids[(v, c)], f"k/{v}/{c}", 100, "ab" * 32, 0.01) for c in cues])
            assert len(done) == len(cues)
            t3 = time.process_time()
            for k, dt in zip(spent, (t1 - t0, t2 - t1, t3 - t2), strict=True):
                spent[k] += dt
        with sm() as s:
            assert all(set(states) == {"done"} for states in job_progress(s, job_id).values())
    per_view = {f"{k}_ms": round(1000 * v / views, 3) for k, v in spent.items()}
    per_view["total_ms"] = round(sum(1000 * v / views for v in spent.values()), 3)
    per_view["tasks_per_view"] = len(cues)
    return per_view


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=200)
    ap.add_argument("--label", default="current")
    args = ap.parse_args()
    figures = {"views": args.views, **run(args.views), "load": [round(x, 2) for x in os.getloadavg()]}
    print(json.dumps(figures))
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    results[args.label] = figures
    RESULTS.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
