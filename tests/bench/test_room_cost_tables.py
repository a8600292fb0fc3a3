"""bench/render/room_cost.py's tables: the render process's busy fractions from a run's task rows, and the
segment cues' equivalence decisions read from bench/cues/segment_stability.py's latest run."""

from __future__ import annotations

import json
import sqlite3
import sys

from tests.conftest import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "bench" / "render"))
import room_cost  # noqa: E402

NOISE = {"segment_unsup2d": {"views": 0},
         "segment_unsup25d": {"views": 8, "ari_median": 0.998, "ari_p10": 0.95}}


def _candidate(decision: str) -> dict:
    return {"segment_unsup2d": {"views": 8, "decision": decision},  # no noise floor: left out
            "segment_unsup25d": {"views": 8, "ari_median": 1.0, "ari_p10": 0.99, "decision": decision,
                                 "ms_saved_per_view_median": 5.5}}


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


def test_segment_stability_rows_of_the_latest_run_and_none_from_an_absent_or_foreign_file(tmp_path):
    path = tmp_path / "segment_stability.json"
    assert room_cost.segment_stability(path) == []
    run = {"rooms": {"icl": {"noise_floor": NOISE, "candidates": {"shipped": _candidate("PASS"),
                                                                   "c4": _candidate("FAIL")}}}}
    path.write_text(json.dumps({"benchmark": "x", "after": run, "before": {"rooms": {}}}))
    rows = room_cost.segment_stability(path)
    assert [(r["candidate"], r["cue"], r["decision"]) for r in rows] == [
        ("shipped", "segment_unsup25d", "PASS"), ("c4", "segment_unsup25d", "FAIL")]
    assert rows[0]["noise_ari"] == (0.998, 0.95) and rows[0]["candidate_ari"] == (1.0, 0.99)
    assert rows[0]["ms_saved"] == 5.5
    assert any("PASS" in line for line in room_cost.figures_table({"rooms": {}, "segment_stability": rows}))
    for foreign in ("[1, 2]", "not json", json.dumps({"after": {"rooms": {"icl": {"candidates": ["x"]}}}})):
        path.write_text(foreign)
        assert room_cost.segment_stability(path) == []
