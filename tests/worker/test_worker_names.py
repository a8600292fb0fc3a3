"""Worker ids: the name given to `omnidata worker --hostname` (plus -i for pool child i > 0), kept by the
process that replaces a recycled or killed child, which also hands back the tasks its predecessor held."""

from __future__ import annotations

import os
import socket
from datetime import timedelta

import pytest
from billiard import process as billiard_process
from sqlalchemy import update

from services.cli import main
from services.cli.worker import WORKER_NAME_HELD_S, node_name
from services.core.db.models import Task, Worker, utcnow
from services.core.settings import get_settings
from services.worker import tasks
from services.worker.run.heartbeat import live_holder
from services.worker.run.runner import default_worker_id
from tests.worker.run.test_runner import banana, make_job, queue  # noqa: F401  (banana is a fixture)
from tests.worker.test_celery_worker import pg_sm, runtime_reset  # noqa: F401  (fixtures)


def test_node_name_expands_like_celery_and_defaults_to_a_unique_name() -> None:
    host = socket.gethostname()
    assert node_name("gpu1@%h") == f"gpu1@{host}"
    assert node_name("gpu1") == "celery@gpu1"  # what Celery itself names the node
    assert node_name(None).startswith("omnidata-") and node_name(None).endswith(f"@{host}")


def test_worker_id_is_the_name_plus_the_pool_child_index(monkeypatch: pytest.MonkeyPatch) -> None:
    assert default_worker_id("w@h") == "w@h"  # not in a pool (solo, tests)
    me = billiard_process.current_process()
    for index, expected in ((0, "w@h"), (2, "w@h-2")):
        monkeypatch.setattr(me, "index", index, raising=False)
        assert default_worker_id("w@h") == expected
    assert default_worker_id(None) == f"{socket.gethostname()}:{os.getpid()}"


def test_a_named_process_takes_over_its_predecessors_row_and_tasks(pg_url, pg_sm, banana, runtime_reset):  # noqa: F811
    name = f"w-{banana.store.root.parent.name}@test"
    job_id = make_job(pg_sm, banana)
    tid = queue(pg_sm, job_id, "point_info")
    with pg_sm() as s:  # the child that held this name was killed mid-task: its row and its task remain
        s.execute(update(Task).where(Task.id == tid).values(
            state="running", worker_id=name, lease_until=utcnow() + timedelta(minutes=5)))
        s.add(Worker(id=name, host="h", queues=["render"], last_heartbeat=utcnow() - timedelta(seconds=40),
                     tasks_done=5, labels={"rgb": 5}))
        s.commit()
    settings = get_settings(database_url=pg_url, storage_url=banana.store.root.as_uri(), lease_s=60)
    runtime = tasks.build_runtime(settings, queues=["render"], name=name)
    try:
        assert runtime.runner.worker_id == name and runtime.heartbeat.worker_id == name
        runtime.heartbeat.record_done("rgb", 1)
        runtime.heartbeat.beat()
    finally:
        runtime.close()
    with pg_sm() as s:
        task = s.get(Task, tid)
        # reaper's now
        assert task is not None and task.lease_until is not None and task.lease_until < utcnow()
        row = s.get(Worker, name)
        assert row is not None and row.tasks_done == 6 and row.labels == {"rgb": 6}
        assert (utcnow() - row.last_heartbeat).total_seconds() < 30


def test_a_name_alive_on_another_host_is_refused(pg_url, pg_sm, monkeypatch, tmp_path, capsys):  # noqa: F811
    name = f"w-{tmp_path.name}@{socket.gethostname()}"
    with pg_sm() as s:
        s.add(
            Worker(
                id=name, host="another-host", queues=["render"],
                last_heartbeat=utcnow() - timedelta(seconds=3),
            )
        )
        s.commit()
    monkeypatch.setenv("OMNIDATA_DATABASE_URL", pg_url)
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(tmp_path))
    assert main(["worker", "--hostname", name]) == 2
    assert f"a worker named {name!r} is alive on another-host" in capsys.readouterr().err
    with pg_sm() as s:  # gone quiet: the name is free again (this would start the worker, so only the check)
        s.execute(
            update(Worker).where(Worker.id == name).values(last_heartbeat=utcnow() - timedelta(minutes=5))
        )
        s.commit()
    assert live_holder(pg_sm, name, within_s=WORKER_NAME_HELD_S) is None
