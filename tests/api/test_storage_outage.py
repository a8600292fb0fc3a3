"""A full object folder through the real API app: /ready says "storage full", and a job held for its store
reads as paused by the store with the reason, until the scheduler's StoreWatch sees space back. On a real full
tmpfs and a database of the test's own (a held job fails /ready for everyone using that database)."""

from __future__ import annotations

from pathlib import Path

from services.core.db.engine import downgrade, migrate
from services.core.db.jobs import hold_for_storage
from services.core.storage import LocalStore, StorageUnavailable
from services.scheduler.store_watch import StoreWatch
from tests.fixtures.api import fake_plan, make_api
from tests.fixtures.small_disk import fill, small_tmpfs


def test_ready_and_the_job_say_storage_full_until_space_returns(empty_pg_url: str, tmp_path: Path,
                                                                 bunny: Path) -> None:
    migrate(empty_pg_url)
    with small_tmpfs(tmp_path / "disk", 16) as disk, make_api(empty_pg_url, LocalStore(disk)) as api:
        sid = api.client.post("/spaces", files={"file": ("b.ply", bunny.read_bytes())},
                              headers=api.a.headers).json()["id"]
        job_id = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}},
                                 headers=api.a.headers).json()["id"]
        with api.session() as s:
            fake_plan(s, job_id)
        assert api.client.get("/ready").status_code == 200

        ballast = fill(disk)
        api.app.state.storage_probe = None  # past the probe's few seconds of caching
        r = api.client.get("/ready", headers=api.a.headers)
        assert r.status_code == 503 and r.json()["failed"] == ["storage"], r.text
        assert "storage full" in r.json()["detail"]
        assert api.client.get("/ready").json()["failed"] == ["storage"]  # no token: the name, not the reason

        try:  # what a worker does when the store refuses a view's outputs (services.worker.run.claim)
            api.store.put_bytes("jobs/x/rgb/a.png", b"x" * 100_000)
        except StorageUnavailable as e:
            problem = str(e)
        with api.session() as s:
            assert hold_for_storage(s, job_id, problem)
            s.commit()
        for read in (api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json(),
                     api.client.get("/jobs", headers=api.a.headers).json()["items"][0]):
            assert read["state"] == "paused" and read["paused_by"] == "storage", read
            assert read["error"].startswith("storage full: no space left in the object folder")
            assert "resumes on its own" in read["error"]

        ballast.unlink()
        api.app.state.storage_probe = None
        r = api.client.get("/ready", headers=api.a.headers)  # space back, but a job still waits: not ready
        assert r.status_code == 503 and "1 job(s) wait for the store" in r.json()["detail"], r.text
        assert StoreWatch(api.sessions, api.store, interval_s=0.0).check() == [job_id]
        api.app.state.storage_probe = None
        assert api.client.get("/ready").status_code == 200
        read = api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()
        assert (read["state"], read["paused_by"], read["error"]) == ("running", None, None)

        # an owner's pause of a held job is the owner's: the store's return does not resume it
        with api.session() as s:
            hold_for_storage(s, job_id, problem)
            s.commit()
        assert api.client.post(f"/jobs/{job_id}/pause", headers=api.a.headers).status_code in (200, 202, 204)
        assert StoreWatch(api.sessions, api.store, interval_s=0.0).check() == []
        assert api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()["paused_by"] is None
    downgrade(empty_pg_url, "base")


def test_deleting_a_job_removes_the_temp_files_its_killed_writers_left(pg_url: str, local_store: LocalStore,
                                                                      bunny: Path) -> None:
    with make_api(pg_url, local_store) as api:
        sid = api.client.post("/spaces", files={"file": ("b.ply", bunny.read_bytes())},
                              headers=api.a.headers).json()["id"]
        job = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}},
                              headers=api.a.headers).json()
        with api.session() as s:
            fake_plan(s, job["id"])
        root = api.client.get(f"/jobs/{job['id']}", headers=api.a.headers).json()["output_root"].strip("/")
        local_store.put_bytes(f"{root}/rgb/x/a.png", b"done")
        # a writer killed mid-write left its temp file
        left = local_store.root / root / "rgb" / "x" / ".b.png.tmp-0123456789abcdef0123456789abcdef"
        left.write_bytes(b"partial")
        assert api.client.delete(f"/jobs/{job['id']}", headers=api.a.headers).status_code == 204
        assert not left.exists() and not (local_store.root / root).exists()
