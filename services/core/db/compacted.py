"""Reading compacted views (`view_output` rows) next to task rows, and expanding them back into task rows.

Readers of done tasks (manifest, views API, resume, the generate report) read both: a view's done tasks are
either its task rows or, once compaction packed them, its `view_output` row, never both.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any

from sqlalchemy import ColumnElement, delete, insert, select, tuple_
from sqlalchemy.orm import Session

from services.core.db.durations import add_durations
from services.core.db.models import Job, JobSpace, Space, Task, TaskState, ViewOutput
from services.core.db.view_outputs import CUE_INDEX, DoneTask, as_task, keys_of, unpack
from services.core.domain.cues import CATALOG

ViewKey = tuple[int, int, int]  # space, point, view
EXPAND_CHUNK = 500  # views per query when expanding


def space_names(session: Session, job_id: int) -> dict[int, str]:
    """The job's spaces, id -> name."""
    return {
        int(i): str(n)
        for i, n in session.execute(
            select(Space.id, Space.name)
            .join(JobSpace, JobSpace.space_id == Space.id)
            .where(JobSpace.job_id == job_id)
        )
    }


def has_compacted(session: Session, job_id: int) -> bool:
    """Whether any view of the job is compacted."""
    return session.scalar(select(ViewOutput.job_id).where(ViewOutput.job_id == job_id).limit(1)) is not None


def cue_filter(cue: str) -> ColumnElement[bool]:
    """SQL condition: the compacted view holds a task of `cue`."""
    return ViewOutput.cue_mask.op("&")(1 << CUE_INDEX[cue]) != 0


def iter_compacted(
    session: Session, job: Job, *where: ColumnElement[bool], names: dict[int, str] | None = None,
) -> Iterator[tuple[ViewKey, list[DoneTask]]]:
    """((space, point, view), its done tasks) of the job's compacted views matching `where`, in view order."""
    names = names if names is not None else space_names(session, job.id)
    rows = session.execute(
        select(ViewOutput.space_id, ViewOutput.point_idx, ViewOutput.view_idx, ViewOutput.outputs)
        .where(ViewOutput.job_id == job.id, *where)
        .order_by(ViewOutput.space_id, ViewOutput.point_idx, ViewOutput.view_idx)
    )
    for s, p, v, data in rows:
        s, p, v = int(s), int(p), int(v)
        yield (s, p, v), unpack(data, keys_of(job, names[s], p, v))


def compacted_tasks(session: Session, job: Job, *where: ColumnElement[bool]) -> list[Task]:
    """The done tasks of the job's compacted views matching `where`, as transient Task objects."""
    return [
        as_task(t, job.id, s, p, v)
        for (s, p, v), tasks in iter_compacted(session, job, *where)
        for t in tasks
    ]


def expand_views(session: Session, job: Job, keys: Iterable[ViewKey]) -> int:
    """Put compacted views back as task rows (done, new ids, their recorded outputs) and drop their compact
    rows; the counters are unchanged (the tasks were counted done all along). Returns the number of task rows
    made."""
    keys = sorted(set(keys))
    names = space_names(session, job.id)
    made = 0
    for i in range(0, len(keys), EXPAND_CHUNK):
        part = keys[i : i + EXPAND_CHUNK]
        cond = tuple_(ViewOutput.space_id, ViewOutput.point_idx, ViewOutput.view_idx).in_(part)
        rows: list[dict[str, Any]] = [
            {
                "job_id": job.id, "space_id": s, "point_idx": p, "view_idx": v, "cue": t.cue,
                "state": TaskState.DONE, "attempts": t.attempts, "output_key": t.output_key, "size": t.size,
                "sha256": t.sha256, "duration_s": t.duration_s, "finished_at": t.finished_at,
            }
            for (s, p, v), tasks in iter_compacted(session, job, cond, names=names)
            for t in tasks
        ]
        session.execute(delete(ViewOutput).where(ViewOutput.job_id == job.id, cond))
        add_durations(session, job.id, [(r["cue"], r["duration_s"]) for r in rows], sign=-1)
        if rows:
            session.execute(insert(Task), rows)
        made += len(rows)
    session.flush()
    return made


def expand_missing(session: Session, job: Job, exists: Callable[[str], bool]) -> int:
    """Expand the compacted views with a public output whose file is gone (`exists(key)` false), so that a
    resume finds their tasks as rows and makes those outputs again; returns the number of views expanded."""
    missing = [
        key for key, tasks in iter_compacted(session, job)
        if any(not CATALOG[t.cue].internal and (not t.output_key or not exists(t.output_key)) for t in tasks)
    ]
    expand_views(session, job, missing)
    return len(missing)
