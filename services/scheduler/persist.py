"""Persist a space's plan: cameras, points, views and compiled tasks (bulk COPY), counters, plan JSON.

A plan is written chunk by chunk (`persist_chunk`, into the caller's transaction: one per chunk), and its
JSON is written piece by piece to a temporary file (`PlanJsonFile`), byte for byte `plan_to_json` of the
whole plan. A planner that dies leaves some chunks of its job: the next attempt starts with `clear_plan`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.bulk import bulk_insert
from services.core.db.counters import init_counts
from services.core.db.jobs import root_key
from services.core.db.models import (
    Camera,
    CompactedDuration,
    Job,
    JobCounter,
    JobState,
    Point,
    Task,
    View,
    ViewOutput,
)
from services.core.domain.plan import CameraRecord, SpacePlan, plan_to_dict, plan_to_json
from services.core.storage import ObjectStore
from services.core.temp_dirs import owned_temp_dir
from services.scheduler.compile import CompiledTasks


@dataclass(frozen=True)
class PersistedSpace:
    """Rows written for one space of a job."""

    cameras: int
    points: int
    views: int
    tasks: int
    plan_key: str


def plan_key(job: Job, space_name: str) -> str:
    """Store key of a space's plan JSON: `<output_root>/_plan/<space name>.json`."""
    return root_key(job, f"_plan/{space_name}.json")


def clear_plan(session: Session, job_id: int) -> None:
    """Delete every planned row of a job (a re-plan after a planner died starts from nothing)."""
    for model in (Task, ViewOutput, CompactedDuration, View, Point, Camera, JobCounter):
        session.execute(delete(model).where(model.job_id == job_id))


def drop_cancelled_plan(sm: sessionmaker[Session], job_id: int) -> None:
    """Remove the chunks a stopped planner wrote for a job cancelled while planning (a cancel leaves them
    to the planner's side: see cancel_job). The key lock waits for the planner's open chunk to end."""
    with sm() as s:
        stmt = select(Job.state).where(Job.id == job_id)
        if s.get_bind().dialect.name == "postgresql":
            stmt = stmt.with_for_update()
        if s.scalar(stmt) == JobState.CANCELLED:
            clear_plan(s, job_id)
        s.commit()


def plan_rows(plan: SpacePlan, job_id: int, space_id: int) -> tuple[dict, dict, dict]:
    """Column dicts of the camera, point and view rows of a plan (metres, radians, world frame)."""
    cams, pts, views = plan.cameras, plan.points, plan.views
    cam_pos = np.array([c.position for c in cams], dtype=np.float64).reshape(-1, 3)
    cameras = {
        "job_id": [job_id] * len(cams),
        "space_id": [space_id] * len(cams),
        "idx": [c.idx for c in cams],
        "x": cam_pos[:, 0], "y": cam_pos[:, 1], "z": cam_pos[:, 2],
        "source": [c.source for c in cams],
        "uuid": [c.uuid for c in cams],
    }
    n_views = np.zeros(len(pts), dtype=np.int64)
    if views and pts:  # a chunk's points are consecutive: count by offset from its first
        first = pts[0].idx
        counted = np.bincount(
            np.fromiter((v.point_idx - first for v in views), dtype=np.int64, count=len(views)),
            minlength=len(pts),
        )
        n_views[: len(counted)] = counted[: len(pts)]
    pos = np.array([p.position for p in pts], dtype=np.float64).reshape(-1, 3)
    nrm = np.array([p.normal for p in pts], dtype=np.float64).reshape(-1, 3)
    points = {
        "job_id": [job_id] * len(pts),
        "space_id": [space_id] * len(pts),
        "idx": [p.idx for p in pts],
        "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
        "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2],
        "n_views": n_views,
        "uuid": [p.uuid for p in pts],
    }
    view_rows = {
        "job_id": [job_id] * len(views),
        "space_id": [space_id] * len(views),
        "point_idx": [v.point_idx for v in views],
        "v": [v.v for v in views],
        "camera_idx": [v.camera_idx for v in views],
        "fov": [float(v.fov) for v in views],
        "roll": [float(v.roll) for v in views],
        "resolution": [int(v.resolution) for v in views],
        "obliqueness": [float(v.obliqueness) for v in views],
        "world_to_camera": [
            np.asarray(v.world_to_camera, dtype=np.float64).reshape(16).tolist() for v in views
        ],
        "in_sight": [bool(v.in_sight) for v in views],
    }
    return cameras, points, view_rows


def persist_space(
    session: Session,
    store: ObjectStore,
    job: Job,
    space_id: int,
    plan: SpacePlan,
    tasks: CompiledTasks,
) -> PersistedSpace:
    """Write one space's plan rows, its task rows (state pending) and counters, and its plan JSON."""
    cameras, points, views = plan_rows(plan, job.id, space_id)
    bulk_insert(session, Camera, cameras)
    bulk_insert(session, Point, points)
    bulk_insert(session, View, views)
    n_tasks = bulk_insert(session, Task, tasks.columns(job.id))
    init_counts(session, job.id, tasks.counts)
    key = plan_key(job, plan.space_name)
    store.put_bytes(key, plan_to_json(plan).encode("utf-8"), content_type="application/json")
    return PersistedSpace(len(plan.cameras), len(plan.points), len(plan.views), n_tasks, key)


def persist_chunk(
    session: Session, job_id: int, space_id: int, chunk: SpacePlan, tasks: CompiledTasks
) -> int:
    """Write one chunk of a space's plan (cameras, points, views), its task rows (pending) and their counts;
    returns the number of tasks."""
    cameras, points, views = plan_rows(chunk, job_id, space_id)
    bulk_insert(session, Camera, cameras)
    bulk_insert(session, Point, points)
    bulk_insert(session, View, views)
    n_tasks = bulk_insert(session, Task, tasks.columns(job_id))
    init_counts(session, job_id, tasks.counts)
    return n_tasks


def _dumps(item: object) -> str:
    """One element as plan_to_json writes it."""
    return json.dumps(item, sort_keys=True, separators=(",", ":"), allow_nan=False)


class PlanJsonFile:
    """A plan's JSON built from its chunks in temporary files (points and views kept apart: `plan_to_json`
    sorts the keys, and the plan's own fields come between them); `finish` gives the file of the whole
    text."""

    def __init__(self) -> None:
        self._dir = owned_temp_dir("plan")  # named after this planner: swept if it is killed
        self._cameras: list[CameraRecord] = []
        self._parts = {name: open(Path(self._dir.name) / name, "w", encoding="utf-8")  # noqa: SIM115
                       for name in ("points", "views")}
        self._first = {"points": True, "views": True}

    def add(self, chunk: SpacePlan) -> None:
        data = plan_to_dict(chunk)
        self._cameras.extend(data["cameras"])
        for name in ("points", "views"):
            for item in data[name]:
                self._write(name, self._parts[name], item)

    def _write(self, name: str, out: TextIO, item: object) -> None:
        out.write(("" if self._first[name] else ",") + _dumps(item))
        self._first[name] = False

    def finish(self, whole: SpacePlan) -> Path:
        """The whole plan's JSON file (`whole`: the plan's own fields, no cameras, points or views)."""
        marker = {"points": "\x00points\x00", "views": "\x00views\x00"}  # stand-ins, replaced by the files
        head = {**plan_to_dict(whole), "cameras": self._cameras, **{name: [m] for name, m in marker.items()}}
        text = _dumps(head)
        path = Path(self._dir.name) / "plan.json"
        with open(path, "w", encoding="utf-8") as out:
            rest = text
            for name in ("points", "views"):  # sorted keys: points come before views
                before, rest = rest.split(_dumps(marker[name]), 1)
                out.write(before)
                self._parts[name].close()
                with open(Path(self._dir.name) / name, encoding="utf-8") as part:
                    while block := part.read(1 << 20):
                        out.write(block)
            out.write(rest)
        return path

    def close(self) -> None:
        for part in self._parts.values():
            part.close()
        self._dir.cleanup()
