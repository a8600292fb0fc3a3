"""services.core.db.states: every allowed task and job transition works (tasks move, counters follow in the
same transaction), and every other one is refused without touching a row."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.db.bulk import bulk_insert
from services.core.db.counters import add_counts, job_progress
from services.core.db.models import Job, JobState, Task, TaskState
from services.core.db.states import (
    JOB_EDGES,
    TASK_EDGES,
    IllegalTransition,
    check_job_edge,
    counted_sql,
    set_job_state,
    task_update_sql,
    transition,
)

TASK_PAIRS = [(a, b) for a, b in itertools.product(TaskState, TaskState)]
JOB_PAIRS = [(a, b) for a, b in itertools.product(JobState, JobState)]


def _job_with_tasks(session: Session, state: TaskState, n: int = 3) -> Job:
    job = Job(owner="t", name="j", spec={})
    session.add(job)
    session.flush()
    bulk_insert(session, Task, {"job_id": [job.id] * n, "space_id": [1] * n, "point_idx": list(range(n)),
                                "view_idx": [0] * n, "cue": ["rgb"] * n, "state": [state.value] * n})
    add_counts(session, job.id, {("rgb", state.value): n})
    return job


def _truth(session: Session, job_id: int) -> dict[str, int]:
    return dict(session.execute(
        select(Task.state, func.count()).where(Task.job_id == job_id).group_by(Task.state)).all())


def test_every_state_has_a_row_in_the_tables() -> None:
    assert set(TASK_EDGES) == set(TaskState) and set(JOB_EDGES) == set(JobState)
    # final states are final, except that done/failed work can be reopened (resume, retry)
    assert TASK_EDGES[TaskState.CANCELLED] == frozenset() and JOB_EDGES[JobState.CANCELLED] == frozenset()


@pytest.mark.parametrize(("src", "dst"), TASK_PAIRS, ids=[f"{a}->{b}" for a, b in TASK_PAIRS])
def test_task_transition(sqlite_session: Session, src: TaskState, dst: TaskState) -> None:
    job = _job_with_tasks(sqlite_session, src)
    ids = list(sqlite_session.scalars(select(Task.id).where(Task.job_id == job.id).order_by(Task.id)))
    if dst in TASK_EDGES[src]:
        moved = transition(sqlite_session, job_id=job.id, task_ids=ids[:2], from_state=src, to_state=dst)
        assert sorted(i for i, _ in moved) == ids[:2]
        expected = {src.value: 1, dst.value: 2}
    else:
        with pytest.raises(IllegalTransition, match=f"from '{src.value}' to '{dst.value}'"):
            transition(sqlite_session, job_id=job.id, task_ids=ids, from_state=src, to_state=dst)
        expected = {src.value: 3}
    assert _truth(sqlite_session, job.id) == expected
    assert job_progress(sqlite_session, job.id) == {"rgb": expected}


def test_transition_of_all_tasks_and_with_a_condition(sqlite_session: Session) -> None:
    job = _job_with_tasks(sqlite_session, TaskState.RUNNING, n=4)
    sqlite_session.execute(Task.__table__.update().where(Task.point_idx < 1).values(worker_id="me"))
    mine = transition(sqlite_session, job_id=job.id, from_state=TaskState.RUNNING, to_state=TaskState.DONE,
                      where=[Task.worker_id == "me"])
    assert len(mine) == 1
    rest = transition(sqlite_session, job_id=job.id, from_state=TaskState.RUNNING, to_state=TaskState.PENDING)
    assert len(rest) == 3
    assert job_progress(sqlite_session, job.id) == {"rgb": {"done": 1, "pending": 3}} == {"rgb": _truth(
        sqlite_session, job.id)}


def test_a_state_name_that_does_not_exist_is_refused(sqlite_session: Session) -> None:
    job = _job_with_tasks(sqlite_session, TaskState.PENDING)
    with pytest.raises(ValueError):
        transition(sqlite_session, job_id=job.id, from_state="pending", to_state="lost")


def test_the_fixed_sql_builder_takes_only_edges_of_the_table() -> None:
    with pytest.raises(IllegalTransition, match="from 'done' to 'running'"):
        task_update_sql([TaskState.QUEUED, TaskState.DONE], TaskState.RUNNING, "worker_id = :w",
                        "task.id = :id")
    sql = task_update_sql([TaskState.RUNNING], TaskState.DONE, "size = :size", "task.id = :id")
    assert sql.startswith("UPDATE task SET state = 'done', size = :size WHERE task.id = :id "
                          "AND task.state = 'running'")
    pg = counted_sql(sql, "'running'", TaskState.DONE, before="v AS (SELECT '1'::int AS a), ")
    assert "size = %(size)s WHERE task.id = %(id)s" in pg and "'1'::int" in pg and ":size" not in pg


@pytest.mark.parametrize(("src", "dst"), JOB_PAIRS, ids=[f"{a}->{b}" for a, b in JOB_PAIRS])
def test_job_transition(src: JobState, dst: JobState) -> None:
    job = Job(owner="t", name="j", spec={}, state=src.value)
    if dst in JOB_EDGES[src]:
        set_job_state(job, dst, error="why")
        assert job.state == dst and job.error == "why"
        assert check_job_edge(src, dst) == (src, dst)
    else:
        with pytest.raises(IllegalTransition, match=f"job transition from '{src.value}' to '{dst.value}'"):
            set_job_state(job, dst, error="why")
        assert job.state == src and job.error is None


def test_no_state_is_assigned_outside_the_states_module() -> None:
    # "Where does a task or a job change state?": services/core/db/states.py (the planner's conditional claim
    # UPDATE in core/db/jobs.py checks its edge there first), and a worker's own moves as fixed SQL beside it
    # (core/db/worker_moves.py, whose `x.state = '...'` are SQL conditions).
    root = Path(__file__).resolve().parents[3] / "services"
    assign = re.compile(r"\.state\s*=(?!=)")
    offenders = [
        f"{path.relative_to(root)}:{n}"
        for path in root.rglob("*.py")
        if path.relative_to(root).as_posix() not in ("core/db/states.py", "core/db/worker_moves.py")
        for n, line in enumerate(path.read_text().splitlines(), 1) if assign.search(line)
    ]
    assert offenders == []
