"""Test helpers for the API: an app per test with fresh tenants, a fake planner, task completion, a live server.

The fake planner does what the scheduler's planning step does to the database (cameras, points, views,
tasks, counters; job -> running) so API tests do not depend on the scheduler package; task state changes
go through services.core.db.transition like the real worker's, so the counters stay exact.
"""

from __future__ import annotations

import contextlib
import io
import logging
import secrets
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

import numpy as np
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.core.cues import CATALOG, closure
from services.core.db import bulk_insert, init_counts
from services.core.jobs import job_spaces, root_key
from services.core.keys import output_key
from services.core.models import Camera, Job, Point, Task, View, utcnow
from services.core.settings import hash_token
from services.core.states import transition
from services.core.storage import ObjectStore


@dataclass
class Tenant:
    """A tenant with its clear-text token."""

    name: str
    token: str

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}


def new_tenants(n: int = 2) -> list[Tenant]:
    """Fresh tenants with random names (tests share one database and stay apart by tenant)."""
    return [Tenant(f"t{i}-{secrets.token_hex(4)}", secrets.token_urlsafe(24)) for i in range(n)]


def token_map(tenants: list[Tenant]) -> dict[str, str]:
    """Settings.api_tokens for `tenants`."""
    return {hash_token(t.token): t.name for t in tenants}


@dataclass
class Api:
    """An app under test: client, tenants, store, and a session factory on the same database."""

    app: FastAPI
    client: TestClient
    a: Tenant
    b: Tenant
    store: ObjectStore
    sessions: sessionmaker[Session]
    extra: dict[str, Any] = field(default_factory=dict)

    def session(self) -> Session:
        return self.sessions()


def png_bytes(value: int = 128, size: int = 8, bits16: bool = False) -> bytes:
    """A small PNG (8-bit RGB, or 16-bit grey)."""
    buf = io.BytesIO()
    if bits16:
        Image.fromarray(np.full((size, size), value * 257, dtype=np.uint16)).save(buf, format="PNG")
    else:
        Image.fromarray(np.full((size, size, 3), value, dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def fake_plan(
    session: Session, job_id: int, *, points: int = 2, views: int = 2, cameras: int = 4
) -> dict[str, int]:
    """Plan a pending job like the scheduler would: rows for every space, tasks pending, job running."""
    job = session.get(Job, job_id)
    assert job is not None
    pending: dict[str, int] = {}
    rng = np.random.default_rng(job_id)
    for js, sp in job_spaces(session, job_id):
        bulk_insert(
            session,
            Camera,
            [
                {"job_id": job_id, "space_id": sp.id, "idx": c, "x": float(np.cos(c)), "y": float(np.sin(c)),
                 "z": 1.0, "yaw": float(c), "roll": 0.0, "source": "generated", "uuid": f"cam-{c}"}
                for c in range(cameras)
            ],
        )
        bulk_insert(
            session,
            Point,
            [
                {"job_id": job_id, "space_id": sp.id, "idx": p, "x": float(rng.uniform(-0.5, 0.5)),
                 "y": float(rng.uniform(-0.5, 0.5)), "z": 0.1, "nx": 0.0, "ny": 0.0, "nz": 1.0,
                 "n_views": views, "uuid": f"pt-{p}"}
                for p in range(points)
            ],
        )
        w2c = np.eye(4).reshape(-1).tolist()
        bulk_insert(
            session,
            View,
            [
                {"job_id": job_id, "space_id": sp.id, "point_idx": p, "v": v, "camera_idx": (p + v) % cameras,
                 "fov": 1.35, "roll": 0.05, "resolution": 8, "obliqueness": 0.3, "world_to_camera": w2c,
                 "in_sight": True}
                for p in range(points)
                for v in range(views)
            ],
        )
        rows = []
        for p in range(points):
            for v in range(views):
                for cue in closure(js.cues):
                    if CATALOG[cue].per_point and v != 0:
                        continue
                    rows.append({"job_id": job_id, "space_id": sp.id, "point_idx": p, "view_idx": v, "cue": cue})
                    pending[cue] = pending.get(cue, 0) + 1
        bulk_insert(session, Task, rows)
    init_counts(session, job_id, pending)
    job.state = "running"
    job.started_at = utcnow() - timedelta(seconds=10)
    job.total_tasks = sum(pending.values())
    session.commit()
    return pending


def task_ids(session: Session, job_id: int, *, state: str | None = None, cue: str | None = None) -> list[int]:
    """Ids of the job's tasks, optionally by state and cue, in id order."""
    q = select(Task.id).where(Task.job_id == job_id).order_by(Task.id)
    if state is not None:
        q = q.where(Task.state == state)
    if cue is not None:
        q = q.where(Task.cue == cue)
    return list(session.scalars(q).all())


def run_tasks(
    session: Session,
    store: ObjectStore | None,
    job_id: int,
    ids: list[int],
    *,
    fail: bool = False,
    worker: str = "test-worker:1",
) -> None:
    """Move tasks pending -> queued -> running -> done (writing a PNG/JSON output) or -> failed, as a worker would."""
    now = utcnow()
    transition(session, job_id=job_id, task_ids=ids, from_state="pending", to_state="queued", queued_at=now)
    transition(
        session, job_id=job_id, task_ids=ids, from_state="queued", to_state="running",
        worker_id=worker, started_at=now, attempts=Task.attempts + 1,
    )
    job = session.get(Job, job_id)
    assert job is not None
    if fail:
        transition(
            session, job_id=job_id, task_ids=ids, from_state="running", to_state="failed",
            error="RuntimeError: the test made this task fail", finished_at=utcnow(), duration_s=0.5,
        )
        session.commit()
        return
    names = {sp.id: sp.name for _js, sp in job_spaces(session, job_id)}
    for t in session.scalars(select(Task).where(Task.id.in_(ids))).all():
        key = root_key(job, output_key(t.cue, job.name, names[t.space_id], t.point_idx, t.view_idx))
        ext = CATALOG[t.cue].ext
        data = png_bytes(40 + 10 * (t.id % 20), bits16=CATALOG[t.cue].dtype == "uint16") if ext == "png" else b"{}"
        info = store.put_bytes(key, data) if store is not None else None
        transition(
            session, job_id=job_id, task_ids=[t.id], from_state="running", to_state="done",
            output_key=key, size=None if info is None else info.size, sha256=None if info is None else info.sha256,
            finished_at=utcnow(), duration_s=0.2 + 0.01 * (t.id % 7),
        )
    session.commit()


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def live_server(app: FastAPI, *, access_log: bool = False) -> Iterator[str]:
    """Run `app` with uvicorn on 127.0.0.1 in a thread; yields the base URL."""
    port = free_port()
    config = uvicorn.Config(
        app, host="127.0.0.1", port=port, log_level="info" if access_log else "warning", access_log=access_log,
        timeout_graceful_shutdown=1, log_config=None,
    )
    if access_log:  # an earlier Config(access_log=False) switched propagation off for the whole process
        logging.getLogger("uvicorn.access").propagate = True
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)


@contextlib.contextmanager
def make_api(pg_url: str, store: ObjectStore, **overrides: Any) -> Iterator[Api]:
    """An app on the test database and `store`, with two fresh tenants; settings overrides win."""
    from services.api.app import SSEConfig, create_app
    from services.core.settings import get_settings

    a, b = new_tenants(2)
    values: dict[str, Any] = {
        "database_url": pg_url,
        "storage_url": "file:///unused",  # the store object is passed in
        "broker_url": "redis://127.0.0.1:6379/15",
        "api_tokens": token_map([a, b]),
    }
    values.update(overrides)
    settings = get_settings(**values)
    app = create_app(settings, store=store, sse=SSEConfig(poll_s=0.1, heartbeat_s=0.5))
    with TestClient(app, raise_server_exceptions=False) as client:
        yield Api(app=app, client=client, a=a, b=b, store=store, sessions=app.state.sessionmaker)
