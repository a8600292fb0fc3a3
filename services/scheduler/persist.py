"""Persist a space's plan: cameras, points, views and compiled tasks (bulk COPY), counters, plan JSON.

Everything goes into the caller's transaction; nothing commits here, so a planner that dies leaves no
half-planned job (another planner re-plans it from scratch after `clear_plan`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sqlalchemy import delete
from sqlalchemy.orm import Session

from services.core.db.bulk import bulk_insert
from services.core.db.counters import init_counts
from services.core.db.jobs import root_key
from services.core.db.models import Camera, Job, JobCounter, Point, Task, View
from services.core.domain.plan import SpacePlan, plan_to_json
from services.core.storage import ObjectStore
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
    for model in (Task, View, Point, Camera, JobCounter):
        session.execute(delete(model).where(model.job_id == job_id))


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
    if views:
        counted = np.bincount(np.fromiter((v.point_idx for v in views), dtype=np.int64, count=len(views)),
                              minlength=len(pts))
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
        "world_to_camera": [np.asarray(v.world_to_camera, dtype=np.float64).reshape(16).tolist() for v in views],
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
