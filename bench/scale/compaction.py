"""Compaction of finished views (services.scheduler.compaction): bytes per view before and after, and its
rate.

Persists a big_job-style job (`--views` views x the 18 cues of an unlabelled room, 4 views a point) through
the product's bulk path, finishes every task as workers would leave it (the deterministic output key with the
job's root, size, a 64-hex sha256, duration, finish time two minutes ago), VACUUM FULL, and measures the task
table per view; then runs the scheduler's Compactor (its own passes, `compact_pass_s` each) until nothing is
left, timing wall, this process's CPU and the Postgres backends' CPU (/proc; autovacuum off on task meanwhile,
the VACUUM the deleted rows need timed on its own after), VACUUM FULL again and measures task +
view_output (+ compacted_duration) per view, with the starter dataset's extrapolation. It also times the
manifest (iter_manifest_lines) over task rows and over compacted views, and checks that they are
byte-identical.

Writes `compaction` into bench/results/compaction.json (other keys kept) and drops its database.
Run: .venv/bin/python bench/scale/compaction.py [--views 40000]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from sqlalchemy import text

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.scale_cost import ROOM_CUES  # noqa: E402
from bench.scale.big_job import STARTER_VIEWS, persist  # noqa: E402
from bench.scale.fanout import create_database, drop_database, labelled_space  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.db.jobs import create_job  # noqa: E402
from services.core.db.manifest import iter_manifest_lines  # noqa: E402
from services.core.db.models import Job, Space  # noqa: E402
from services.core.db.view_outputs import default_key  # noqa: E402
from services.core.domain.cues import CATALOG  # noqa: E402
from services.core.domain.jobspec import JobSpec  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.scheduler.compaction import Compactor  # noqa: E402

RESULTS = results_dir()


def finish_like_workers(sm: Any, job_id: int, root: str, space: str, component: str) -> float:
    """Every task done with the key a worker records (root + deterministic key), finished two minutes ago."""
    cues = ", ".join(f"('{name}', '{c.ext}', {str(c.per_point).lower()}, {str(c.internal).lower()})"
                     for name, c in CATALOG.items())
    base = f"'{root}/' || t.cue || '/{component}/{space}/point_' || t.point_idx"
    key = (
        f"CASE WHEN c.internal THEN '{root}/_cache/passes/{space}/point_' || t.point_idx || '_view_' "
        f"|| t.view_idx || '.npz' WHEN c.per_point THEN {base} || '_domain_' || t.cue || '.' || c.ext "
        f"ELSE {base} || '_view_' || t.view_idx || '_domain_' || t.cue || '.' || c.ext END"
    )
    t0 = time.perf_counter()
    with sm() as s:
        s.execute(
            text(
                "UPDATE task t SET state = 'done', worker_id = 'w-' || (t.id % 1000), attempts = 1, "
                f"output_key = {key}, "
                "size = 40000 + t.id % 1000, sha256 = md5(t.id::text) || md5(t.cue), duration_s = "
                "0.05 + (t.id % 7) / 100.0, "
                "queued_at = now() - interval '3 minutes', started_at = now() - interval '2 minutes', "
                f"finished_at = now() - interval '2 minutes' FROM (VALUES {cues}) AS c(cue, ext, "
                "per_point, internal) WHERE c.cue = t.cue AND t.job_id = :j"
            ),
            {"j": job_id},
        )
        s.execute(text("UPDATE job_counter SET state = 'done' WHERE job_id = :j"), {"j": job_id})
        s.execute(text("UPDATE job SET state = 'done', finished_at = now() WHERE id = :j"), {"j": job_id})
        s.commit()
        job = s.get(Job, job_id)
        assert job is not None
        for cue, p, v, k in s.execute(text("SELECT cue, point_idx, view_idx, output_key FROM task "
                                           "WHERE job_id = :j ORDER BY id LIMIT 40"), {"j": job_id}):
            assert k == default_key(job, space, cue, p, v), (k, default_key(job, space, cue, p, v))
    return time.perf_counter() - t0


def vacuum(db_url: str, *tables: str) -> None:
    engine = make_engine(db_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as c:
        for t in tables:
            c.execute(text(f"VACUUM FULL {t}"))
    engine.dispose()


def vacuum_cpu_s(db_url: str) -> float:
    """CPU seconds of a plain VACUUM of the task table (what autovacuum spends on the deleted rows)."""
    engine = make_engine(db_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as c:
        pid = int(c.execute(text("SELECT pg_backend_pid()")).scalar_one())

        def cpu() -> float:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        c0 = cpu()
        c.execute(text("VACUUM task"))
        used = cpu() - c0
    engine.dispose()
    return used


def table_bytes(sm: Any, table: str) -> int:
    with sm() as s:
        return int(s.scalar(text(f"SELECT pg_total_relation_size('{table}')")) or 0)


def backends_cpu_s(sm: Any) -> float:
    """CPU seconds (user + system) so far of every Postgres backend connected to this database."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    with sm() as s:
        pids = [int(p) for (p,) in s.execute(text(
            "SELECT pid FROM pg_stat_activity WHERE datname = current_database()"))]
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])
        except (OSError, IndexError, ValueError):
            pass
    return total / tick


def manifest_pass(sm: Any, job_id: int) -> tuple[str, float, float]:
    """sha256 of the job's manifest, wall and CPU seconds to build it."""
    h = hashlib.sha256()
    t0, c0 = time.perf_counter(), time.process_time()
    with sm() as s:
        job = s.get(Job, job_id)
        assert job is not None
        for line in iter_manifest_lines(s, job):
            h.update(line.encode())
    return h.hexdigest(), time.perf_counter() - t0, time.process_time() - c0


def compact_all(sm: Any, pass_s: float) -> dict[str, Any]:
    """Compactor passes until one compacts nothing; wall, CPU of this process and of the Postgres backends."""
    comp = Compactor(sm, after_s=60.0, pass_s=pass_s)
    views = tasks = passes = 0
    pg0 = backends_cpu_s(sm)
    t0, c0 = time.perf_counter(), time.process_time()
    pass_ms = []
    while True:
        t = time.perf_counter()
        res = comp.run_once()
        pass_ms.append(1000 * (time.perf_counter() - t))
        passes += 1
        views += res.views
        tasks += res.tasks
        if res.views == 0:
            break
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    pg = backends_cpu_s(sm) - pg0  # connections opened meanwhile stay in the pool, so their CPU is counted
    return {"views": views, "task_rows": tasks, "passes": passes, "pass_s": pass_s, "wall_s": round(wall, 1),
            "views_per_s_wall": round(views / wall), "cpu_s_compactor_process": round(cpu, 2),
            "cpu_s_postgres": round(pg, 2), "cpu_ms_per_view": round(1000 * (cpu + pg) / max(views, 1), 3),
            "views_per_cpu_s": round(views / max(cpu + pg, 1e-9)), "pass_ms_max": round(max(pass_ms), 1)}


def main(argv: list[str] | None = None) -> int:
    """Persist, finish, measure, compact, measure; write `compaction` into compaction.json; drop the
    database."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, default=40_000)
    p.add_argument("--chunk-views", type=int, default=20_000)
    p.add_argument(
        "--pass-s", type=float, default=0.25, help="compact_pass_s: time one compaction pass may take"
    )
    p.add_argument("--key", default="compaction")
    p.add_argument("--out", type=Path, default=RESULTS / "compaction.json")
    args = p.parse_args(argv)
    db_url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="omnidata-compaction-"))
    doc: dict[str, Any] = {
        "cues": len(ROOM_CUES), "views": args.views, "load_avg_1m_start": round(os.getloadavg()[0], 2),
    }
    try:
        migrate(db_url)
        engine = make_engine(db_url, pool_size=2)
        sm = make_sessionmaker(engine)
        space_id = labelled_space(sm, LocalStore(tmp / "objects"), "big")
        with sm() as s:
            job = create_job(
                s, owner="bench", spec=JobSpec(cues=ROOM_CUES, name="big"), spaces=[s.get(Space, space_id)]
            )
            s.commit()
            job_id, root = job.id, job.output_root
        doc["persist"] = persist(sm, job_id, space_id, args.views, args.chunk_views)
        rows = doc["persist"]["task_rows"]
        doc["finish_s"] = round(finish_like_workers(sm, job_id, root, "big", "big"), 1)
        vacuum(db_url, "task")
        before = table_bytes(sm, "task")
        sha_rows, wall_rows, cpu_rows = manifest_pass(sm, job_id)
        with sm() as s:  # the vacuum the deletes need is measured on its own, after
            s.execute(text("ALTER TABLE task SET (autovacuum_enabled = false)"))
            s.commit()
        doc["compact"] = compact_all(sm, args.pass_s)
        doc["compact"]["vacuum_task_cpu_s"] = round(vacuum_cpu_s(db_url), 2)
        print(json.dumps(doc["compact"]), flush=True)
        vacuum(db_url, "task", "view_output", "compacted_duration")
        after = {t: table_bytes(sm, t) for t in ("task", "view_output", "compacted_duration")}
        sha_packed, wall_packed, cpu_packed = manifest_pass(sm, job_id)
        assert sha_packed == sha_rows, "the manifest changed with compaction"
        view_bytes = table_bytes(sm, "view")
        per_view_before, per_view_after = before / args.views, sum(after.values()) / args.views
        doc["size"] = {
            "finished_task_bytes_per_view": round(per_view_before, 1),
            "finished_task_bytes_per_row": round(before / rows, 1),
            "compacted_bytes_per_view": round(per_view_after, 1),
            "compacted_tables_bytes": after,
            "view_row_bytes_per_view": round(view_bytes / args.views, 1),
            "ratio": round(per_view_before / per_view_after, 2),
            "starter_dataset_extrapolation": {
                "views": STARTER_VIEWS,
                "finished_task_table_gb": round(STARTER_VIEWS * per_view_before / 1e9, 1),
                "compacted_gb": round(STARTER_VIEWS * per_view_after / 1e9, 1),
                "view_table_gb": round(STARTER_VIEWS * view_bytes / args.views / 1e9, 1),
                "compaction_cpu_h": round(STARTER_VIEWS / doc["compact"]["views_per_cpu_s"] / 3600, 2),
            },
        }
        doc["manifest"] = {
            "identical": True, "task_rows": {"wall_s": round(wall_rows, 2), "cpu_s": round(cpu_rows, 2)},
            "compacted": {"wall_s": round(wall_packed, 2), "cpu_s": round(cpu_packed, 2)},
        }
        doc["load_avg_1m_end"] = round(os.getloadavg()[0], 2)
        engine.dispose()
    finally:
        drop_database(db_url)
    out = json.loads(args.out.read_text()) if args.out.exists() else {"benchmark": "compaction"}
    out[args.key] = doc
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
