"""`omnidata generate --render-workers R`: R of the W local workers render (the render queue first, storing
each pass set), the others only derive and never load Blender; the same files byte for byte as every worker
rendering, and each view derived in one batch from its pass set, read once."""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import queue
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.cli.main import main
from services.core import gpu_devices
from services.core.domain.cues import CATALOG
from services.core.settings import get_settings
from services.embedded.job import embedded_settings, worker_pool
from services.embedded.pool import RENDER_AHEAD_VIEWS, TaskQueues, ahead_budget
from services.scheduler.transport import QueueTransport
from tests.fixtures.cli import REPO, dataset_files, done_tasks, omnidata

SPEC = """
cameras: {mode: object, object_count: 6}
points: {count: 3, min_views: 2, max_views: 2}
views: {resolution: 32}
"""


def _delivered(*queues: object) -> None:
    """Wait until each multiprocessing queue's feeder thread has written to its pipe (puts deliver in the
    background), then a moment for the rest of the batch it writes."""
    deadline = time.monotonic() + 10
    while any(q.empty() for q in queues) and time.monotonic() < deadline:  # type: ignore[attr-defined]
        time.sleep(0.01)
    time.sleep(0.1)


def test_the_render_queue_gets_the_renders_and_a_renderer_takes_them_first():
    qs = TaskQueues(mp.get_context("spawn"), split=True)
    QueueTransport(qs.derive, qs.render).send([(1, "rgb"), (2, "passes"), (3, "point_info"), (4, "passes")])
    _delivered(qs.render, qs.derive)
    assert [qs.next_for("render")[0] for _ in range(3)] == [2, 4, 1]  # the renders first, then what waits
    assert qs.next_for("derive")[0] == 3
    with pytest.raises(queue.Empty):
        qs.next_for("derive", timeout=0.1)  # a worker that only derives never takes a render
    QueueTransport(qs.derive, qs.render).send([(5, "passes")])
    with pytest.raises(queue.Empty):
        qs.next_for("derive", timeout=0.3)
    assert qs.next_for("render", timeout=0.3) == (5, qs.render)

    one = TaskQueues(mp.get_context("spawn"), split=False)  # every worker renders: one queue, in order
    assert one.render is one.derive and one.all() == (one.derive,)
    QueueTransport(one.derive, one.render).send([(1, "rgb"), (2, "passes")])
    assert [one.next_for("all")[0] for _ in range(2)] == [1, 2]


def test_a_renderer_past_its_budget_derives_while_derive_work_waits_and_renders_when_none_does():
    qs = TaskQueues(mp.get_context("spawn"), split=True)
    send = QueueTransport(qs.derive, qs.render).send
    send([(1, "passes"), (2, "rgb")])
    _delivered(qs.render, qs.derive)
    assert qs.next_for("render")[0] == 1  # within its budget: the render, though derive work waits
    qs.count(handed=RENDER_AHEAD_VIEWS, read=0)  # the derivers fell RENDER_AHEAD_VIEWS views behind
    send([(3, "passes")])
    _delivered(qs.render)
    assert qs.next_for("render")[0] == 2  # past it: the derive work first ...
    assert qs.next_for("render", timeout=0.3)[0] == 3  # ... and a render when no derive work waits
    qs.count(handed=0, read=1)  # one pass set read back: within the budget again
    send([(4, "rgb"), (5, "passes")])
    _delivered(qs.render, qs.derive)
    assert [qs.next_for("render")[0] for _ in range(2)] == [5, 4]
    assert qs.ahead.value == RENDER_AHEAD_VIEWS - 1
    # on 16 workers of which 2 render, each of the 14 derivers has 2 views waiting for it
    assert ahead_budget(2, 1) == RENDER_AHEAD_VIEWS and ahead_budget(16, 2) == 28


def _maps_mention(pid: int, name: str) -> bool:
    return name in Path(f"/proc/{pid}/maps").read_text()


@pytest.mark.bpy
def test_a_worker_that_only_derives_never_loads_blender(tmp_path):
    settings = get_settings(database_url=f"sqlite:///{tmp_path / 'absent' / 'state.db'}", render_workers=1)
    pool = worker_pool(tmp_path / "out", settings, 2)
    assert [pool.role_of(i) for i in range(2)] == ["render", "derive"]
    pool.start(held=True)
    try:
        renderer, deriver = pool.procs
        deadline = time.monotonic() + 120
        while not _maps_mention(renderer.pid, "bpy/") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _maps_mention(renderer.pid, "bpy/"), "the renderer did not load Blender"
        # the deriver had as long as the renderer to import everything it ever will before a task
        time.sleep(2.0)
        assert deriver.is_alive() and not _maps_mention(deriver.pid, "bpy/")
    finally:
        pool.stop()


def generate(scene: Path, out: Path, spec: Path, *extra: str) -> None:
    res = omnidata(
        "generate", scene, "--out", out, "--spec", spec, "--seed", 3, "--workers", 2, "--name", "split",
        "--no-progress",
        *extra,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr


@pytest.mark.bpy
def test_renderers_and_derivers_give_the_same_files_as_every_worker_rendering(
    scenes_dir: Path, tmp_path: Path
):
    spec = tmp_path / "job.yaml"
    spec.write_text(SPEC)
    whole, split = tmp_path / "whole", tmp_path / "split"
    generate(scenes_dir / "ycb_banana", whole, spec)  # on CPU cores every worker renders by default
    generate(scenes_dir / "ycb_banana", split, spec, "--render-workers", "1")
    assert dataset_files(whole) == dataset_files(split)  # manifest, plan, every cue file

    with sqlite3.connect(split / ".omnidata" / "state.db") as db:
        rows = db.execute(
            "SELECT point_idx, view_idx, cue, worker_id, started_at, size, sha256, attempts, state FROM task"
        ).fetchall()
    assert {r[8] for r in rows} == {"done"} and {r[7] for r in rows} == {1}  # each task run once
    passes = [r for r in rows if r[2] == "passes"]
    assert len(passes) == 6 and len({r[3] for r in passes}) == 1  # one renderer rendered every view ...
    assert all(r[5] > 0 for r in passes)  # ... and stored each pass set for the derivers (raw: no sha256)
    # The claim of a cue read straight from the pass set took the view's last DAG level with it (pending
    # then): the view is derived from one read of its pass set, not one batch per level. Two idle workers may
    # take two of a view's messages at once and split its first level: the last level then waits for the
    # input left with the other worker (handed back, claimed after it), so those views are left out, and they
    # can only be a few (under load, the first view of the job was).
    first_level = {c for c in CATALOG if CATALOG[c].inputs == ("passes",)}
    views = {(r[0], r[1]) for r in passes}
    split = 0
    for view in views:
        claims = {(r[3], r[4]) for r in rows if (r[0], r[1]) == view and r[2] in first_level}
        last = [(r[3], r[4]) for r in rows if (r[0], r[1]) == view and r[2] == "segment_unsup25d"]
        assert len(last) == 1, (view, last)
        if len({worker for worker, _ in claims}) > 1:
            split += 1
            continue
        assert last[0] in claims, (view, last, claims)
    assert split <= len(views) // 2, (split, len(views))


def test_render_workers_out_of_range_are_refused_and_nothing_is_created(
    capsys, scenes_dir, tmp_path, monkeypatch
):
    out = tmp_path / "out"
    banana = scenes_dir / "ycb_banana"
    for args, message in (
        (["--render-workers", "0"], "--render-workers must be at least 1, got 0"),
        (
            ["--workers", "2", "--render-workers", "3"],
            "--render-workers 3 is more than the 2 worker(s) of this run",
        ),
    ):
        code = main(["generate", str(banana), "--out", str(out), "--no-progress", *args])
        err = capsys.readouterr().err
        assert code == 2 and message in err, err
    monkeypatch.setenv("OMNIDATA_RENDER_WORKERS", "4")
    code = main(["generate", str(banana), "--out", str(out), "--no-progress", "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 2 and "OMNIDATA_RENDER_WORKERS 4 is more than the 1 worker(s)" in err, err
    assert not out.exists()


@pytest.fixture
def gpu_machine(tmp_path, monkeypatch):
    """A machine whose driver made /dev/nvidia0 (and the control file, which is no GPU), seen through a
    folder."""
    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "nvidiactl").touch()
    monkeypatch.setattr(gpu_devices, "NVIDIA_DEVICE_NODES", str(dev / "nvidia[0-9]*"))
    monkeypatch.delenv("OMNIDATA_RENDER_WORKERS", raising=False)
    monkeypatch.delenv("OMNIDATA_RENDER_DEVICE", raising=False)
    return dev


def test_on_a_gpu_one_worker_in_eight_renders_unless_told(gpu_machine, tmp_path, monkeypatch):
    out = tmp_path / "out"
    assert embedded_settings(out, 16).render_workers is None  # only the control file: no GPU, all render
    (gpu_machine / "nvidia0").touch()
    assert [embedded_settings(out, w).render_workers for w in (1, 2, 8, 16, 24)] == [None, 1, 1, 2, 3]
    pool = worker_pool(out, embedded_settings(out, 16), 16)  # not started: the roles it would give
    assert [pool.role_of(i) for i in range(16)] == ["render"] * 2 + ["derive"] * 14
    assert embedded_settings(out, 16, render_workers=5).render_workers == 5  # --render-workers
    monkeypatch.setenv("OMNIDATA_RENDER_WORKERS", "16")  # every worker renders: no split
    assert (
        embedded_settings(out, 16).render_workers == 16
        and not worker_pool(out, embedded_settings(out, 16), 16).queues.split
    )
    monkeypatch.delenv("OMNIDATA_RENDER_WORKERS")
    monkeypatch.setenv("OMNIDATA_RENDER_DEVICE", "cpu")  # renders on the CPU whatever the machine has: all
    assert [embedded_settings(out, w).render_workers for w in (1, 2, 3, 16)] == [None] * 4
    assert [worker_pool(out, embedded_settings(out, 16), 16).role_of(i) for i in range(16)] == ["all"] * 16


def test_generate_says_how_many_workers_render_on_a_gpu(gpu_machine, capsys, tmp_path):
    (gpu_machine / "nvidia0").touch()
    empty = tmp_path / "empty.obj"
    empty.write_text("# no faces\n")  # refused when loaded: the run stops before any render
    code = main(["generate", str(empty), "--out", str(tmp_path / "out"), "--no-progress", "--workers", "2"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "omnidata generate: 1 of the 2 workers render, the others derive" in err, err


def _children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


@pytest.mark.bpy
def test_a_deriver_killed_mid_job_loses_no_work(scenes_dir: Path, tmp_path: Path):
    """Two workers on CPU cores: one renders, one derives (--render-workers 1). The deriver is killed -9 while
    the job runs; its tasks go back to the queue, a new deriver takes them, and every file is made once."""
    spec = tmp_path / "job.yaml"
    spec.write_text(SPEC.replace("count: 3", "count: 12").replace("resolution: 32", "resolution: 128"))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "services.cli", "generate", str(scenes_dir / "ycb_banana"), "--out",
           str(out), "--spec", str(spec), "--seed", "3", "--workers", "2", "--render-workers", "1",
           "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        killed = None
        while killed is None and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
            derivers = [c for c in _children(proc.pid) if not _maps_mention(c, "bpy/")]
            if derivers and done_tasks(out) > 0:
                os.kill(derivers[0], signal.SIGKILL)
                killed = derivers[0]
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert killed is not None, "the job ended before a deriver was seen deriving"
    assert proc.returncode == 0, err
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        states = dict(db.execute("SELECT state, count(*) FROM task GROUP BY state").fetchall())
        workers = {w for (w,) in db.execute("SELECT DISTINCT worker_id FROM task WHERE cue != 'passes'")}
    assert set(states) == {"done"}, states
    assert len(workers) >= 2  # the killed deriver's view went to another process
    views = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert len({(v["point"], v["view"]) for v in views}) == len(views) == 24
    for v in views:
        for o in v["outputs"].values():
            assert hashlib.sha256((out / o["key"]).read_bytes()).hexdigest() == o["sha256"], o["key"]
