"""`omnidata submit`: straight into the configured database and store, and through the real API (HTTP client
against the FastAPI app on Postgres). The distributed runs that follow such jobs to the end are in
tests/e2e."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.exc import OperationalError

from services.cli import CliError, main
from services.cli.spec_args import check_sources
from services.cli.submit import Api, Status, submit_http
from services.core.db.engine import make_engine, make_sessionmaker
from services.core.db.models import Job, JobSpace, Space
from services.core.domain.jobspec import JobSpec

SPEC = "cameras: {mode: object, object_count: 6}\npoints: {count: 1, min_views: 2, max_views: 2}\n"


@pytest.fixture()
def spec_file(tmp_path: Path) -> Path:
    p = tmp_path / "job.yaml"
    p.write_text(SPEC)
    return p


@pytest.fixture()
def embedded_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> str:
    url = f"sqlite:///{tmp_path / 'svc.db'}"
    monkeypatch.setenv("OMNIDATA_DATABASE_URL", url)
    monkeypatch.setenv("OMNIDATA_STORAGE_URL", str(tmp_path / "objects"))
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("OMNIDATA_API_URL", raising=False)
    return url


def test_submit_to_the_database_prints_the_id_and_reuses_the_space(
    capsys, embedded_env, spec_file, scenes_dir
):
    banana = scenes_dir / "ycb_banana"
    assert (
        main(["submit", str(banana), "--spec", str(spec_file), "--no-follow", "--owner", "ana", "--direct"])
        == 0
    )
    first = int(capsys.readouterr().out.strip())
    assert (
        main(
            [
                "submit", str(banana), "--spec", str(spec_file), "--seed", "5", "--no-follow", "--owner",
                "ana", "--direct",
            ]
        )
        == 0
    )
    out = capsys.readouterr()
    second = int(out.out.strip())
    assert "registered space" not in out.err  # same name, same content: reused
    engine = make_engine(embedded_env)
    with make_sessionmaker(engine)() as s:
        jobs = {j.id: j for j in s.scalars(select(Job))}
        assert set(jobs) == {first, second}
        assert jobs[first].state == "pending" and jobs[first].owner == "ana"
        assert jobs[first].output_root == f"jobs/{first}" and jobs[second].spec["seed"] == 5
        spaces = s.scalars(select(Space)).all()
        assert [sp.name for sp in spaces] == ["ycb_banana"]
        assert {js.space_id for js in s.scalars(select(JobSpace))} == {spaces[0].id}
    engine.dispose()


def test_follow_ends_with_the_job_and_exit_1_unless_done(capsys, embedded_env, spec_file, scenes_dir):
    from services.core.db.jobs import cancel_job

    engine = make_engine(embedded_env)
    sm = make_sessionmaker(engine)

    def cancel_soon() -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                with sm() as s:
                    job = s.scalars(select(Job)).first()
                    if job is not None:
                        cancel_job(s, job)
                        s.commit()
                        return
            except OperationalError:  # not migrated yet
                pass
            time.sleep(0.1)

    t = threading.Thread(target=cancel_soon)
    t.start()
    code = main(
        ["submit", str(scenes_dir / "ycb_banana"), "--spec", str(spec_file), "--interval", "0.1", "--direct"]
    )
    t.join()
    engine.dispose()
    out = capsys.readouterr()
    assert code == 1
    assert "cancelled" in out.err and out.out.strip().isdigit()


def test_submit_refuses_bad_input_before_sending_anything(capsys, embedded_env, tmp_path, scenes_dir):
    code = main(["submit", str(tmp_path / "none.ply"), "--spec", str(tmp_path / "none.yaml"), "--direct"])
    assert code == 2 and "no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("views: {resolution: 1}\n")
    code = main(["submit", str(scenes_dir / "ycb_banana"), "--spec", str(bad), "--direct"])
    assert code == 2 and "views.resolution" in capsys.readouterr().err
    assert not Path(embedded_env.removeprefix("sqlite:///")).exists()


def test_submit_without_a_service_says_so_and_writes_nothing(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, spec_file: Path,
    scenes_dir: Path,
) -> None:
    for var in ("OMNIDATA_API_URL", "OMNIDATA_DATABASE_URL"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(tmp_path / "data"))  # where the embedded SQLite would go
    banana = str(scenes_dir / "ycb_banana")
    assert main(["submit", banana, "--spec", str(spec_file), "--no-follow"]) == 2
    err = capsys.readouterr().err
    assert "no service configured" in err and "--api" in err and len(err.strip().splitlines()) == 1
    assert main(["submit", banana, "--spec", str(spec_file), "--no-follow", "--direct"]) == 2
    assert "--direct needs OMNIDATA_DATABASE_URL" in capsys.readouterr().err
    assert not (tmp_path / "data").exists()


def test_submit_over_http_uploads_once_and_reads_progress(pg_url, local_store, scenes_dir):
    from tests.fixtures.api import live_server, make_api

    spec = JobSpec.model_validate({"cameras": {"mode": "object", "object_count": 6},
                                   "points": {"count": 1, "min_views": 2, "max_views": 2}})
    sources = check_sources([str(scenes_dir / "ycb_banana")])
    with make_api(pg_url, local_store) as a, live_server(a.app) as base:
        api = Api(base, a.a.token)
        job_id = submit_http(api, spec, sources)
        st = api.status(job_id)
        assert isinstance(st, Status) and st.state == "pending" and st.total == 0
        assert f"job {job_id} pending" in st.line(job_id)
        again = submit_http(api, spec, sources)  # the uploaded space is found by name and checksum
        assert again != job_id
        spaces = a.client.get("/spaces", headers=a.a.headers).json()
        assert [sp["name"] for sp in spaces["items"]] == ["ycb_banana"]
        assert spaces["items"][0]["source_key"].endswith(".zip")  # the .obj went up with its .mtl and texture
        api.client.headers["Authorization"] = "Bearer wrong"
        with pytest.raises(CliError, match="401"):
            api.status(job_id)


def test_submit_takes_the_spec_flags_with_or_without_a_spec_file(capsys, pg_url, local_store, scenes_dir,
                                                                 spec_file):
    from tests.fixtures.api import live_server, make_api

    banana = str(scenes_dir / "ycb_banana")
    with make_api(pg_url, local_store) as a, live_server(a.app) as base:
        given = ["--api", base, "--token", a.a.token, "--no-follow"]
        assert main(["submit", banana, "--points", "3", "--resolution", "64", "--cues", "rgb,normal",
                     "--seed", "5", *given]) == 0  # no --spec: the defaults and the flags
        bare = int(capsys.readouterr().out.strip())
        assert main(["submit", banana, "--spec", str(spec_file), "--points", "2", "--name", "fruit",
                     *given]) == 0
        over = int(capsys.readouterr().out.strip())  # the flags override the file's fields, the rest stays
        with a.session() as s:
            bare_spec, over_spec = (JobSpec.model_validate(s.get(Job, i).spec) for i in (bare, over))
    assert (bare_spec.points.count, bare_spec.views.resolution, bare_spec.seed) == (3, 64, 5)
    assert bare_spec.cues == ["rgb", "normal"] and bare_spec.cameras == JobSpec().cameras
    assert (over_spec.points.count, over_spec.points.min_views, over_spec.name) == (2, 2, "fruit")
    assert over_spec.cameras.mode == "object" and over_spec.cameras.object_count == 6
