"""bench/render/room_cost.py's tables: the render process's busy fractions from a run's task rows, and the
segment-stability decision table read from another benchmark's results, whatever form they are in."""

from __future__ import annotations

import json
import sqlite3
import sys

from tests.conftest import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "bench" / "render"))
import room_cost  # noqa: E402

CANDIDATE = {"cpu_s_saved_per_view_median": 0.01,
             "segment_unsup2d": {"views": 0},
             "segment_unsup25d": {"views": 8, "within_bound": 1.0}}


def test_the_render_process_is_the_one_that_rendered_and_its_busy_share_is_of_wall_and_window(tmp_path):
    db = sqlite3.connect(tmp_path / "state.db")
    db.execute("CREATE TABLE task (worker_id TEXT, cue TEXT, duration_s REAL, started_at TEXT, "
               "finished_at TEXT, state TEXT)")
    rows = [("r", "passes", 1.0, "2026-01-01 00:00:00", "2026-01-01 00:00:01"),
            ("r", "passes", 1.0, "2026-01-01 00:00:01", "2026-01-01 00:00:02"),
            ("r", "rgb", 0.5, "2026-01-01 00:00:02", "2026-01-01 00:00:03"),
            ("d", "rgb", 3.0, "2026-01-01 00:00:01", "2026-01-01 00:00:04")]
    db.executemany("INSERT INTO task VALUES (?, ?, ?, ?, ?, 'done')", rows)
    busy = room_cost.busy_fractions(db, wall=8.0)
    assert busy["task_window_s"] == 4.0
    assert (busy["render_busy_of_wall"], busy["render_busy_of_task_window"]) == (0.25, 0.5)
    assert busy["render_process_busy_of_task_window"] == 0.625
    assert [p["views_rendered"] for p in busy["processes"]] == [2, 0]


def test_segment_stability_rows_from_either_form_and_none_from_an_absent_or_foreign_file(tmp_path):
    path = tmp_path / "segment_stability.json"
    assert room_cost.segment_stability(path) == []
    run = {"rooms": {"icl": {"candidates": {"c4": CANDIDATE, "bad": {**CANDIDATE, "segment_unsup25d": {
        "views": 8, "within_bound": 0.875}}}}}}
    for doc in ({"benchmark": "x", "after": run}, run):
        path.write_text(json.dumps(doc))
        rows = room_cost.segment_stability(path)
        assert [(r["candidate"], r["decision"]) for r in rows] == [("c4", "holds"), ("bad", "refused")]
        assert rows[0]["within_bound"] == {"segment_unsup25d": 1.0}  # a cue with no views is left out
    for foreign in ("[1, 2]", "not json", json.dumps({"rooms": {"icl": {"candidates": ["x"]}}})):
        path.write_text(foreign)
        assert room_cost.segment_stability(path) == []
