"""The task routes over compacted views (services.scheduler.compaction): their done tasks come from
`view_output` rows, listed after the task rows, found by id, and counted in the throughput at their view's
finish time."""

from __future__ import annotations

from collections.abc import Iterator
from itertools import islice

from sqlalchemy import ColumnElement, func, select
from sqlalchemy.orm import Session

from services.api.pagination import PageParams
from services.core.db.compacted import cue_filter, iter_compacted
from services.core.db.models import Job, Task, TaskState, ViewOutput
from services.core.db.view_outputs import as_task


def _compacted_where(cue: str | None, space_id: int | None) -> list[ColumnElement[bool]]:
    where: list[ColumnElement[bool]] = []
    if cue is not None:
        where.append(cue_filter(cue))
    if space_id is not None:
        where.append(ViewOutput.space_id == space_id)
    return where


def iter_compacted_tasks(session: Session, job: Job, cue: str | None, space_id: int | None) -> Iterator[Task]:
    """The done tasks of the job's compacted views (of `cue`, in `space_id`), in view order, then cue
    order."""
    for (s, p, v), tasks in iter_compacted(session, job, *_compacted_where(cue, space_id)):
        for t in tasks:
            if cue is None or t.cue == cue:
                yield as_task(t, job.id, s, p, v)


def compacted_count(session: Session, job: Job, cue: str | None, space_id: int | None) -> int:
    """Done tasks held in the job's compacted views (of `cue`, in `space_id`): bits of their cue masks."""
    masks = session.execute(
        select(ViewOutput.cue_mask, func.count())
        .where(ViewOutput.job_id == job.id, *_compacted_where(cue, space_id))
        .group_by(ViewOutput.cue_mask)
    )
    return sum((1 if cue is not None else int(m).bit_count()) * int(n) for m, n in masks)


def page_with_compacted(
    session: Session, job: Job, cond: list[ColumnElement[bool]], page: PageParams, cue: str | None,
    space_id: int | None,
) -> list[Task]:
    """A page of the task rows matching `cond` (by id) followed by the compacted views' done tasks (in view
    order).

    Reaching into the compacted part costs the views skipped (offset paging over packed rows)."""
    rows = list(
        session.scalars(select(Task).where(*cond).order_by(Task.id).limit(page.limit).offset(page.offset))
    )
    if len(rows) == page.limit:
        return rows
    n_rows = int(session.scalar(select(func.count()).select_from(Task).where(*cond)) or 0)
    skip = max(0, page.offset - n_rows)
    return rows + list(
        islice(iter_compacted_tasks(session, job, cue, space_id), skip, skip + page.limit - len(rows))
    )


def find_compacted_task(session: Session, job: Job, task_id: int) -> Task | None:
    """A compacted task by its id (a walk over the job's packed views: rare, and bounded by the job's
    size)."""
    for (s, p, v), tasks in iter_compacted(session, job):
        for t in tasks:
            if t.id == task_id:
                return as_task(t, job.id, s, p, v)
    return None


def done_states(state: str | None) -> bool:
    """Whether a task listing in `state` includes done tasks (so compacted ones)."""
    return state is None or state == TaskState.DONE
