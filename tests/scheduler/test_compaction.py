# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Compaction: finished views' task rows become one view_output row each, and every reader still sees them."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from sqlalchemy import func, select, update

from services.core.db.compacted import compacted_tasks, expand_views, space_names
from services.core.db.counters import job_progress
from services.core.db.jobs import delete_job, reopen_job
from services.core.db.manifest import manifest_bytes
from services.core.db.models import CompactedDuration, Job, Task, ViewOutput
from services.core.db.states import transition
from services.core.db.view_outputs import CUE_NAMES, DoneTask, default_key, pack, unpack
from services.core.domain.cues import CATALOG
from services.embedded.report import build_report, views_done
from services.scheduler.compaction import _COLUMNS, Compactor, _compact, _group
from services.scheduler.dispatch import dispatch_once
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import any_sm, finish, make_running_job, pg_sm, sqlite_sm, task_ids  # noqa: F401  (fixtures)


def _run_all(s, job, fail_first_rgb: bool = False):
    for _ in range(20):
        tr = NullTransport()
        dispatch_once(s, tr, window=1000)
        if not tr.sent:
            return
        ids = [i for i, _ in tr.sent]
        if fail_first_rgb:  # view (0, 1)'s rgb fails for good: that view is never compacted
            rgb = s.scalar(
                select(Task.id).where(
                    Task.job_id == job.id, Task.cue == "rgb", Task.point_idx == 0, Task.view_idx == 1,
                    Task.state == "queued",
                )
            )
            if rgb is not None:
                ids.remove(rgb)
                transition(s, job_id=job.id, task_ids=[rgb], from_state="queued", to_state="cancelled")
                s.commit()
        for job_id in {int(j) for j in s.scalars(select(Task.job_id).where(Task.id.in_(ids)))}:
            mine = [int(i) for i in s.scalars(select(Task.id).where(Task.id.in_(ids), Task.job_id == job_id))]
            finish(s, s.get(Job, job_id), mine)


def _default_keys_for_half(s, job):
    """Workers record the deterministic key (with the root) for most tasks; the helper's keys stay on the
    rest."""
    names = space_names(s, job.id)
    for tid, sid, p, v, cue in s.execute(
        select(Task.id, Task.space_id, Task.point_idx, Task.view_idx, Task.cue).where(
            Task.job_id == job.id, Task.id % 2 == 0
        )
    ).all():
        s.execute(
            update(Task).where(Task.id == tid).values(output_key=default_key(job, names[sid], cue, p, v))
        )
    s.commit()


def test_every_cue_has_a_fixed_packed_index():
    assert set(CATALOG) <= set(CUE_NAMES) and len(CUE_NAMES) <= 63  # cue_mask is a BIGINT
    assert CUE_NAMES[:3] == ("passes", "rgb", "normal")  # indexes of stored rows never move


def test_pack_round_trips_every_field():
    when = datetime(2026, 11, 24, 19, 0, 0, 123457, tzinfo=UTC)
    tasks = [
        DoneTask(7, "rgb", 1, "jobs/1/rgb/c/s/point_0_view_0_domain_rgb.png", 1234, "ab" * 32, 0.25, when),
        # upper-case sha kept as text
        DoneTask(8, "passes", 3, "elsewhere/x.npz", None, "AB" * 32, None, None),
        DoneTask(9, "nonfixated", 0, None, 5, None, 1e-7, when + timedelta(days=400)),
    ]

    def key_of(cue):
        return f"jobs/1/{cue}/c/s/point_0_view_0_domain_{cue}.png"
    data = pack(tasks, key_of)
    assert unpack(data, key_of) == tasks
    assert len(data) < 3 * 80 + len("elsewhere/x.npz") + 64 + 8  # ~70 bytes a task plus what is not derivable


def test_compaction_keeps_the_manifest_byte_identical_and_the_counters(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb", "depth_zbuffer", "mask_valid", "nonfixated"],
                               n_points=3, views=3, name="comp")
        _run_all(s, job, fail_first_rgb=True)
        _default_keys_for_half(s, job)
        before_manifest, before_counts = manifest_bytes(s, job), job_progress(s, job.id)
        before_rows = s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job.id))
        before_views = views_done(s, job.id)

    comp = Compactor(any_sm, after_s=3600, chunk_rows=7)  # nothing finished an hour ago
    assert comp.run_once().views == 0
    # chunks smaller than a view's 5 tasks x 2: cut views wait
    comp = Compactor(any_sm, after_s=0, pass_s=60, chunk_rows=7)
    for _ in range(20):
        comp.run_once()
    with any_sm() as s:
        job = s.get(Job, job.id)
        n_compact = s.scalar(select(func.count()).select_from(ViewOutput).where(ViewOutput.job_id == job.id))
        left = s.execute(select(Task.point_idx, Task.view_idx).where(Task.job_id == job.id).distinct()).all()
        # the view with a cancelled task
        assert n_compact == 8 and {(int(p), int(v)) for p, v in left} == {(0, 1)}
        # nonfixated on view 0 of each point
        assert (
            before_rows - s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job.id))
            == 8 * 4 + 3
        )
        assert job_progress(s, job.id) == before_counts
        assert manifest_bytes(s, job) == before_manifest
        assert views_done(s, job.id) == before_views
        tasks = compacted_tasks(s, job)
        assert len(tasks) == 8 * 4 + 3 and all(t.state == "done" and t.sha256 for t in tasks)


def test_resume_expands_a_compacted_view_whose_output_is_gone(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb", "nonfixated"], n_points=2, views=2, name="res")
        _run_all(s, job)
        for t in s.scalars(select(Task).where(Task.job_id == job.id)):
            local_store.put_bytes(t.output_key, b"x")
        job.state = "done"
        s.commit()
        counts = job_progress(s, job.id)
    Compactor(any_sm, after_s=0, pass_s=60).run_once()
    with any_sm() as s:
        job = s.get(Job, job.id)
        assert s.scalar(select(func.count()).select_from(Task).where(Task.job_id == job.id)) == 0
        assert build_report(any_sm, local_store, job.id).outputs == 2 * 2 + 2
        gone = next(
            t for t in compacted_tasks(s, job) if t.cue == "rgb" and (t.point_idx, t.view_idx) == (1, 1)
        )
        local_store.delete(gone.output_key)
        done = reopen_job(s, local_store, job)
        s.commit()
        assert done.redo == 1 and job.state == "running"
        rows = s.execute(
            select(Task.cue, Task.state, Task.point_idx, Task.view_idx).where(Task.job_id == job.id)
        ).all()
        assert sorted((c, str(st)) for c, st, _, _ in rows) == [("passes", "done"), ("rgb", "pending")]
        assert {(int(p), int(v)) for _, _, p, v in rows} == {(1, 1)}
        assert s.scalar(select(func.count()).select_from(ViewOutput).where(ViewOutput.job_id == job.id)) == 3
        moved = dict(counts["rgb"])
        moved["done"] -= 1
        moved["pending"] = 1
        assert job_progress(s, job.id)["rgb"] == moved


def test_expanding_gives_back_the_same_tasks(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=2, views=1)
        _run_all(s, job)
        s.execute(update(Task).values(duration_s=0.3))
        s.commit()
        before = sorted((t.cue, t.point_idx, t.output_key, t.size, t.sha256, t.finished_at)
                        for t in s.scalars(select(Task).where(Task.job_id == job.id)))
    Compactor(any_sm, after_s=0, pass_s=60).run_once()
    with any_sm() as s:
        job = s.get(Job, job.id)
        assert s.execute(select(CompactedDuration.cue, CompactedDuration.bucket, CompactedDuration.n)
                         .order_by(CompactedDuration.cue)).all() == [("passes", 3, 2), ("rgb", 3, 2)]
        assert expand_views(s, job, [(k[0], k[1], k[2]) for k in s.execute(
            select(ViewOutput.space_id, ViewOutput.point_idx, ViewOutput.view_idx))]) == 4
        s.commit()
        after = sorted((t.cue, t.point_idx, t.output_key, t.size, t.sha256, t.finished_at)
                       for t in s.scalars(select(Task).where(Task.job_id == job.id, Task.state == "done")))
        assert after == before
        assert s.scalar(select(func.count()).select_from(ViewOutput)) == 0
        assert s.scalar(select(func.sum(CompactedDuration.n))) == 0


def test_deleting_a_job_deletes_its_compacted_views(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=2, views=2)
        other = make_running_job(s, local_store, cues=["rgb"], n_points=1, views=1)
        _run_all(s, job)
        _run_all(s, other)
        job.state = other.state = "done"
        s.commit()
    Compactor(any_sm, after_s=0, pass_s=60).run_once()
    with any_sm() as s:
        assert s.scalar(select(func.count()).select_from(ViewOutput)) == 5
        delete_job(s, local_store, s.get(Job, job.id))
        s.commit()
        assert [int(j) for j in s.scalars(select(ViewOutput.job_id))] == [other.id]


def test_a_task_taken_back_meanwhile_rolls_the_chunk_back(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=1, views=1)
        _run_all(s, job)
        ids = task_ids(s, job.id)
        views = _group(s.execute(select(*_COLUMNS).where(Task.job_id == job.id)).all(), complete_only=False)
        # a resume moves a task between the compactor's read and its delete
        transition(s, job_id=job.id, task_ids=ids[:1], from_state="done", to_state="pending")
        s.commit()
        assert _compact(s, job.id, views) == (0, 0)
        s.commit()
        assert s.scalar(select(func.count()).select_from(ViewOutput)) == 0
        assert len(task_ids(s, job.id)) == 2


def test_a_running_job_is_walked_from_its_start_and_a_settled_one_not_again(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=10, views=2)
        for _ in range(2):  # passes, then rgb: points 0 and 9 run, the others wait in the queue
            dispatch_once(s, NullTransport(), window=1000)
            finish(s, job, [i for p in (0, 9) for i in task_ids(s, job.id, point_idx=p, state="queued")])
    comp = Compactor(any_sm, after_s=0, pass_s=60, chunk_rows=6)
    for _ in range(3):
        comp.run_once()
    with any_sm() as s:
        packed = {(int(p), int(v)) for p, v in s.execute(select(ViewOutput.point_idx, ViewOutput.view_idx))}
        # point 9 finished too, but a chunk with nothing done sends the walk of a running job back to its
        # start
        assert packed == {(0, 0), (0, 1)}
        s.execute(update(Job).where(Job.id == job.id).values(state="failed"))
        s.commit()
    comp.run_once()
    with any_sm() as s:
        packed = {(int(p), int(v)) for p, v in s.execute(select(ViewOutput.point_idx, ViewOutput.view_idx))}
        assert packed == {(0, 0), (0, 1), (9, 0), (9, 1)}  # a finished job is walked to its end
    # a walk that compacted nothing: the job is settled, not walked again while it stays failed
    comp.run_once()
    assert comp._settled == {job.id: "failed"}
    calls = []
    comp.compact_chunk = lambda *a, **k: calls.append(a) or (0, 0, False)  # type: ignore[method-assign]
    comp.run_once()
    assert calls == []


def test_a_running_job_walk_stops_at_views_finished_but_not_due(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=10, views=2)
        _run_all(s, job)
        old = datetime.now(UTC) - timedelta(hours=2)
        s.execute(update(Task).where(Task.job_id == job.id, Task.point_idx < 2).values(finished_at=old))
        s.commit()
    comp = Compactor(any_sm, after_s=60, pass_s=60, chunk_rows=6)
    chunks = []
    inner = comp.compact_chunk
    comp.compact_chunk = lambda *a, **k: chunks.append(a) or inner(*a, **k)  # type: ignore[method-assign]
    comp.run_once()
    with any_sm() as s:
        packed = {(int(p), int(v)) for p, v in s.execute(select(ViewOutput.point_idx, ViewOutput.view_idx))}
    assert packed == {(p, v) for p in (0, 1) for v in (0, 1)}
    # the chunk of views finished a moment ago ends the walk: points 3-9 are not read (40 rows, 6 a chunk)
    assert len(chunks) == 3
    assert comp._walks[job.id].cursor == (-1, -1, -1)
    # Until the first of them is due (a minute after it finished), passes read nothing at all.
    chunks.clear()
    assert comp.run_once(now=datetime.now(UTC) + timedelta(seconds=30)).chunks == 0
    assert chunks == []
    comp.run_once(now=datetime.now(UTC) + timedelta(seconds=61))  # then the next pass packs them all
    with any_sm() as s:
        assert s.scalar(select(func.count()).select_from(ViewOutput)) == 20
        assert task_ids(s, job.id) == []


def test_a_pass_cut_short_by_its_time_bound_does_not_idle(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb"], n_points=10, views=2)
        _run_all(s, job)
    comp = Compactor(any_sm, after_s=0, pass_s=1e-9, chunk_rows=6)  # every pass stops after its first chunk
    for _ in range(3):
        assert comp.run_once().chunks == 1
    assert comp._idle_until is None
