"""`omnidata generate` with view batches (the default) against one task at a time
(OMNIDATA_WORKER_BATCH_VIEWS=false): the same files byte for byte, one task row per point-view-cue, each run
once, the job's counters exact."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from tests.fixtures.cli import REPO, dataset_files

SPEC = """
cameras: {mode: object, object_count: 6}
points: {count: 2, min_views: 2, max_views: 2}
views: {resolution: 32}
"""


def generate(scene: Path, out: Path, spec: Path, *, batched: bool) -> None:
    env = {**os.environ, "OMNIDATA_WORKER_BATCH_VIEWS": "true" if batched else "false"}
    cmd = [
        sys.executable, "-m", "services.cli", "generate", str(scene), "--out", str(out), "--spec", str(spec),
        "--seed", "3", "--workers", "1", "--name", "batch", "--no-progress",
    ]
    res = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr


def task_rows(out: Path) -> list[tuple]:
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        return db.execute(
            "SELECT space_id, point_idx, view_idx, cue, state, attempts, started_at FROM task"
        ).fetchall()


def counters(out: Path) -> dict[tuple[str, str], int]:
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        rows = db.execute("SELECT cue, state, SUM(n) FROM job_counter GROUP BY cue, state").fetchall()
    return {(cue, state): int(n) for cue, state, n in rows if n}


@pytest.mark.slow
def test_view_batches_give_the_same_files_and_exact_counts(scenes_dir: Path, tmp_path: Path):
    spec = tmp_path / "job.yaml"
    spec.write_text(SPEC)
    outs = {}
    for batched in (True, False):
        outs[batched] = tmp_path / f"batched-{batched}"
        generate(scenes_dir / "ycb_banana", outs[batched], spec, batched=batched)
    assert dataset_files(outs[True]) == dataset_files(outs[False])  # manifest, plan, every cue file

    for batched, out in outs.items():
        rows = task_rows(out)
        keys = [r[:4] for r in rows]
        assert len(keys) == len(set(keys))  # one row per point-view-cue
        assert {(r[4], r[5]) for r in rows} == {("done", 1)}  # each run exactly once
        truth: dict[tuple[str, str], int] = {}
        for r in rows:
            truth[(r[3], r[4])] = truth.get((r[3], r[4]), 0) + 1
        assert counters(out) == truth
        claims = len({r[6] for r in rows})  # a batch's tasks share their claim's time
        assert (claims < len(rows)) if batched else (claims == len(rows))
