"""Compile a space's plan into task rows (pure: no database, no storage, so it is
tested and benchmarked on plans alone).

For every view of the plan, one task per cue in `closure(cues)` (the requested cues plus everything
they depend on, the internal `passes` render included), in topological order within the view so the
oldest-first dispatcher works depth-first. Per-point cues (nonfixated) are one task per point, on its
view 0. Dependencies are data: a task's inputs are the tasks of its catalog inputs on the same
(space, point, view), or on view 0 for per-point inputs.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from services.core.domain.cues import CATALOG, closure
from services.core.domain.plan import SpacePlan


@dataclass(frozen=True)
class CompiledTasks:
    """Task rows of one space as columns (ready for db.bulk_insert) and the number of tasks per cue."""

    space_id: int
    cues: tuple[str, ...]  # closure order
    point_idx: np.ndarray  # int32 (n,)
    view_idx: np.ndarray  # int32 (n,)
    cue: list[str]  # (n,)
    counts: dict[str, int]

    def __len__(self) -> int:
        return len(self.cue)

    def columns(self, job_id: int) -> dict[str, object]:
        """Columns of the `task` table for `job_id` (state and attempts take their defaults)."""
        n = len(self)
        return {
            "job_id": np.full(n, job_id, dtype=np.int64),
            "space_id": np.full(n, self.space_id, dtype=np.int64),
            "point_idx": self.point_idx,
            "view_idx": self.view_idx,
            "cue": self.cue,
        }


def task_cues(cues: Iterable[str]) -> list[str]:
    """The cues that get tasks for requested `cues`: their closure, in topological (catalog) order."""
    return closure(cues)


def compile_tasks(plan: SpacePlan, cues: Iterable[str], space_id: int) -> CompiledTasks:
    """Task rows for every view of `plan` and every cue of closure(cues); per-point cues on v == 0 only."""
    order = task_cues(cues)
    per_view = [c for c in order if not CATALOG[c].per_point]
    n_views = len(plan.views)
    pts = np.fromiter((v.point_idx for v in plan.views), dtype=np.int32, count=n_views)
    vs = np.fromiter((v.v for v in plan.views), dtype=np.int32, count=n_views)
    first = vs == 0
    per_row = np.where(first, len(order), len(per_view)).astype(np.int64)
    point_col = np.repeat(pts, per_row)
    view_col = np.repeat(vs, per_row)
    cue_col = [c for is_first in first.tolist() for c in (order if is_first else per_view)]
    n_first = int(first.sum())
    counts = {c: (n_first if CATALOG[c].per_point else n_views) for c in order}
    counts = {c: n for c, n in counts.items() if n}
    return CompiledTasks(space_id, tuple(order), point_col, view_col, cue_col, counts)


def check_dag(tasks: CompiledTasks) -> list[str]:
    """Problems with a compiled task set: a task whose input task is missing. Empty when complete."""
    have = set(zip(tasks.point_idx.tolist(), tasks.view_idx.tolist(), tasks.cue, strict=True))
    problems = []
    for p, v, c in have:
        for inp in CATALOG[c].inputs:
            target = (p, 0 if CATALOG[inp].per_point else v, inp)
            if target not in have:
                problems.append(f"{c} of point {p} view {v} needs {inp}, which has no task")
    return sorted(problems)
