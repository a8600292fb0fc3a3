"""compile_tasks: one task per view and cue of the closure, per-point cues once per point, DAG complete."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.core.domain.cues import CATALOG, OUTPUT_CUES, default_cues
from services.scheduler.compile import check_dag, compile_tasks
from tests.fixtures.jobs import synthetic_plan


def test_counts_follow_the_closure_and_per_point_cues():
    plan = synthetic_plan("room", n_points=3, views_per_point=4)
    tasks = compile_tasks(plan, ["reshading", "nonfixated"], space_id=7)
    # reshading needs depth_zbuffer and normal, which need the passes render
    assert set(tasks.cues) == {"passes", "normal", "depth_zbuffer", "reshading", "nonfixated"}
    assert tasks.cues.index("reshading") > max(tasks.cues.index("normal"), tasks.cues.index("depth_zbuffer"))
    assert tasks.counts == {"passes": 12, "normal": 12, "depth_zbuffer": 12, "reshading": 12, "nonfixated": 3}
    assert len(tasks) == 4 * 12 + 3
    nonfix = [
        (p, v)
        for p, v, c in zip(tasks.point_idx, tasks.view_idx, tasks.cue, strict=True)
        if c == "nonfixated"
    ]
    assert sorted(nonfix) == [(0, 0), (1, 0), (2, 0)]
    cols = tasks.columns(job_id=42)
    assert set(cols) == {"job_id", "space_id", "point_idx", "view_idx", "cue"}
    assert set(np.asarray(cols["job_id"]).tolist()) == {42} and set(
        np.asarray(cols["space_id"]).tolist()
    ) == {7}
    assert check_dag(tasks) == []


def test_every_view_gets_every_cue_in_topological_order():
    plan = synthetic_plan("room", n_points=5, views_per_point=3)
    tasks = compile_tasks(plan, OUTPUT_CUES, space_id=1)
    assert len(tasks.cues) == len(OUTPUT_CUES) + 1  # + passes
    per_view: dict[tuple[int, int], list[str]] = {}
    for p, v, c in zip(tasks.point_idx.tolist(), tasks.view_idx.tolist(), tasks.cue, strict=True):
        per_view.setdefault((p, v), []).append(c)
    assert len(per_view) == 15
    for (_p, v), cues in per_view.items():
        expected = [c for c in tasks.cues if v == 0 or not CATALOG[c].per_point]
        assert cues == expected  # no duplicates, inputs first
        pos = {c: i for i, c in enumerate(cues)}
        for c in cues:
            assert all(pos[i] < pos[c] for i in CATALOG[c].inputs if i in pos)
    assert check_dag(tasks) == []
    # rows come view by view, in plan order (the dispatcher's oldest-first order is depth-first)
    keys = list(zip(tasks.point_idx.tolist(), tasks.view_idx.tolist(), strict=True))
    assert keys == sorted(keys)


def test_default_cues_of_an_unlabelled_space_have_no_semantic_tasks():
    plan = synthetic_plan("room", n_points=2, views_per_point=2)
    tasks = compile_tasks(plan, default_cues(has_semantics=False), space_id=1)
    assert not {"segment_semantic", "segment_instance", "segment_panoptic"} & set(tasks.cue)
    assert check_dag(tasks) == []


def test_check_dag_reports_a_missing_input():
    plan = synthetic_plan("room", n_points=1, views_per_point=2)
    tasks = compile_tasks(plan, ["rgb"], space_id=1)
    keep = [i for i, c in enumerate(tasks.cue) if not (c == "passes" and tasks.view_idx[i] == 1)]
    broken = dataclasses.replace(
        tasks, point_idx=tasks.point_idx[keep], view_idx=tasks.view_idx[keep],
        cue=[tasks.cue[i] for i in keep],
    )
    assert broken.counts == tasks.counts  # counts are not re-derived: check_dag looks at rows
    assert check_dag(broken) == ["rgb of point 0 view 1 needs passes, which has no task"]


def test_empty_plan_gives_no_tasks_and_unknown_cue_is_refused():
    plan = synthetic_plan("room", n_points=0, views_per_point=2)
    assert len(compile_tasks(plan, ["rgb"], space_id=1)) == 0
    with pytest.raises(ValueError, match="unknown cue"):
        compile_tasks(synthetic_plan("room", 1, 1), ["rgbd"], space_id=1)
