# ruff: noqa: F811  -- the fixtures imported from tests.fixtures.jobs are redefined as test arguments
"""Completion: a finished job gets manifest.jsonl (one line per view) and job.json; failures are
summarised."""

from __future__ import annotations

import json

from sqlalchemy import update

from services.core.db.manifest import job_document, manifest_bytes
from services.core.db.models import Job
from services.core.domain.camera import CONVENTIONS
from services.core.domain.keys import passes_key
from services.scheduler.completion import complete_once, finished_job_ids
from services.scheduler.dispatch import dispatch_once
from services.scheduler.transport import NullTransport
from tests.fixtures.jobs import any_sm, claim, finish, make_running_job, pg_sm, sqlite_sm, task_ids  # noqa: F401  (fixtures)


def _run_all(s, job):
    for _ in range(20):
        tr = NullTransport()
        dispatch_once(s, tr, window=1000)
        if not tr.sent:
            return
        finish(s, job, [i for i, _ in tr.sent])


def test_manifest_has_one_line_per_view_and_the_pass_cache_is_gone(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["rgb", "nonfixated"], n_points=2, views=3, name="comp")
        root = job.output_root
        local_store.put_bytes(f"{root}/{passes_key('x', 0, 0)}", b"cache")
        local_store.put_bytes(f"{root}/rgb/comp/x/keep.png", b"output")
        assert complete_once(s, local_store) == []  # nothing has run yet
        _run_all(s, job)
        assert finished_job_ids(s) == [job.id]
        (fin,) = complete_once(s, local_store)
        assert (fin.job_id, fin.state, fin.error) == (job.id, "done", None)
        s.refresh(job)
        assert job.state == "done" and job.finished_at is not None

        lines = local_store.get_bytes(f"{root}/manifest.jsonl").decode().splitlines()
        entries = [json.loads(x) for x in lines]
        assert [(e["point"], e["view"]) for e in entries] == [(p, v) for p in range(2) for v in range(3)]
        for e in entries:
            assert e["space"].startswith("space-")
            expected = {"rgb", "nonfixated"} if e["view"] == 0 else {"rgb"}
            assert set(e["outputs"]) == expected  # passes is internal: never listed
            rgb = e["outputs"]["rgb"]
            assert rgb["key"] == f"rgb/x/p{e['point']}v{e['view']}"  # relative to the output root
            assert rgb["size"] > 10 and len(rgb["sha256"]) == 64
        assert local_store.get_bytes(f"{root}/manifest.jsonl") == manifest_bytes(s, job)  # rebuildable

        doc = json.loads(local_store.get_bytes(f"{root}/job.json"))
        assert doc["conventions"] == CONVENTIONS
        assert doc["spec"]["cues"] == ["rgb", "nonfixated"]
        assert set(doc["cues"]) == {"rgb", "nonfixated"} and doc["cues"]["rgb"]["ext"] == "png"
        (sp,) = doc["spaces"].values()
        assert sp["source_to_world"] and sp["checksum_sha256"] == "0" * 64
        assert doc["counts"]["by_state"] == {"done": len(task_ids(s, job.id))}
        assert doc["code_version"] and doc["job"]["state"] == "done"
        assert doc == json.loads(json.dumps(job_document(s, job)))

        assert not list(local_store.list(f"{root}/_cache/"))
        assert local_store.exists(f"{root}/rgb/comp/x/keep.png")
        assert complete_once(s, local_store) == []  # finished once


def test_a_failed_task_fails_the_job_with_a_summary(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=3, views=1)
        tr = NullTransport()
        dispatch_once(s, tr, window=1000)
        ids = [i for i, _ in tr.sent]
        finish(s, job, ids[1:])
        claim(s, job.id, ids[:1])
        from services.core.db.states import transition

        transition(s, job_id=job.id, task_ids=ids[:1], from_state="running", to_state="failed",
                   error="RuntimeError: boom\n  File x.py line 3\nRuntimeError: boom at the end")
        s.commit()
        (fin,) = complete_once(s, local_store)
        assert fin.state == "failed"
        assert fin.error.startswith("1 of 3 tasks failed (point_info: 1); first: task")
        assert "RuntimeError: boom" in fin.error
        lines = local_store.get_bytes(f"{job.output_root}/manifest.jsonl").decode().splitlines()
        outs = [json.loads(x)["outputs"] for x in lines]
        assert len(outs) == 3 and sum(1 for o in outs if not o) == 1  # the failed view has no outputs


def test_paused_or_active_jobs_are_not_finished(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1)
        _run_all(s, job)
        s.execute(update(Job).where(Job.id == job.id).values(state="paused"))
        s.commit()
        assert complete_once(s, local_store) == []
        other = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=1)
        assert other.id not in finished_job_ids(s)  # its tasks are all pending


def test_embedded_layout_writes_at_the_store_root(any_sm, local_store):
    with any_sm() as s:
        job = make_running_job(s, local_store, cues=["point_info"], n_points=1, views=2, output_root="")
        assert job.output_root == ""
        _run_all(s, job)
        complete_once(s, local_store)
        assert local_store.exists("manifest.jsonl") and local_store.exists("job.json")
        assert local_store.exists(
            "_plan/" + json.loads(local_store.get_bytes("job.json"))["spaces"].popitem()[0] + ".json"
        )
