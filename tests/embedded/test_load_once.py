"""`omnidata generate` parses each space once in its own process: the scheduler plans from the space the run
validated (Scheduler(loaded_spaces=...)) instead of loading the stored copy again, and the plan is the
same."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import services.cli.generate as generate_cli
import services.core.ingest.parsed_cache as parsed_cache
import services.scheduler.plan_space as plan_space
from services.cli.spec_args import check_sources
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.domain.jobspec import JobSpec
from services.core.storage import LocalStore
from services.embedded.job import STATE_DIR, embedded_settings, prepare_job
from services.scheduler.loop import Scheduler
from services.scheduler.transport import NullTransport

OBJECT_SPEC = {
    "cameras": {"mode": "object", "object_count": 6}, "points": {"count": 2, "min_views": 2, "max_views": 2},
    "views": {"resolution": 16}, "name": "demo",
}
ROOM_SPEC = {"points": {"count": 2, "max_views": 3}, "views": {"resolution": 16}, "name": "demo"}


def plan_job(out: Path, paths: list[Path], spec: JobSpec, *, hand_over: bool) -> dict[str, Any]:
    """Validate, register and plan as `omnidata generate` does (no workers, a user cache of its own: every
    call parses); the plans and task rows it wrote."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("OMNIDATA_DATA_DIR", str(out / "user"))
        return _plan_job(out, paths, spec, hand_over=hand_over)


def _plan_job(out: Path, paths: list[Path], spec: JobSpec, *, hand_over: bool) -> dict[str, Any]:
    settings = embedded_settings(out, 1)
    migrate(settings.database_url)
    engine = make_engine(settings.database_url)
    sessions = make_sessionmaker(engine)
    store = LocalStore(out)
    try:
        sources = check_sources([str(p) for p in paths])
        generate_cli.validate_sources(sources, spec)
        prepared = prepare_job(sessions, store, spec, sources)
        sched = Scheduler(sessions, store, NullTransport(), settings, cache_dir=out / STATE_DIR / "cache",
                          loaded_spaces=prepared.loaded if hand_over else None)
        assert sched.plan_pending() == [prepared.job_id]
        if hand_over:
            # no mesh kept in this process after planning
            assert not prepared.loaded and not sched.loaded_spaces
        with engine.connect() as db:
            rows = sorted(tuple(r) for r in db.exec_driver_sql(
                "SELECT space_id, point_idx, view_idx, cue, state FROM task").fetchall())
            summary = json.loads(db.exec_driver_sql("SELECT plan_summary FROM job").scalar_one())
        summary.pop("planning_s")  # a duration
        plans = {p.name: p.read_bytes() for p in sorted((out / "_plan").glob("*.json"))}
        assert plans
        return {"plans": plans, "tasks": rows, "summary": summary}
    finally:
        engine.dispose()


@pytest.mark.parametrize("room", [False, True], ids=["objects", "icl_room"])
def test_generate_loads_each_space_once_and_plans_the_same(room: bool, scenes_dir: Path, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    loads: list[str] = []

    def counting(real: Any) -> Any:
        def load(path: Any, **kw: Any) -> Any:
            loads.append(Path(path).name)
            return real(path, **kw)
        return load

    monkeypatch.setattr(parsed_cache, "load_space", counting(parsed_cache.load_space))
    monkeypatch.setattr(plan_space, "load_space", counting(plan_space.load_space))
    if room:
        paths, spec = [scenes_dir / "icl_livingroom"], JobSpec.model_validate(ROOM_SPEC)
    else:
        paths = [scenes_dir / "ycb_banana", scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"]
        spec = JobSpec.model_validate(OBJECT_SPEC)
    once = plan_job(tmp_path / "once", paths, spec, hand_over=True)
    assert len(loads) == len(paths)  # validation's load only: planning took it over
    loads.clear()
    twice = plan_job(tmp_path / "twice", paths, spec, hand_over=False)
    assert len(loads) == 2 * len(paths)  # the old path: validation, then the store's copy again
    for key in ("plans", "tasks", "summary"):
        assert once[key] == twice[key], key


def test_generate_reads_the_capture_beside_a_scan_once(scenes_dir: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The 7-Scenes kitchen's capture (500 poses and photos beside the mesh) is looked for by the checksum,
    the validation, the packing and the registering: within generate's captures_kept() it is read once."""
    from services.cli.main import build_parser
    from services.core.ingest.capture import detect

    reads: list[Path] = []
    real = detect.read_sevenscenes
    monkeypatch.setattr(
        detect, "read_sevenscenes", lambda root, files: reads.append(root) or real(root, files)
    )
    kitchen = scenes_dir / "7scenes_redkitchen" / "mesh_tsdf_2cm_from_1000frames.ply"
    spec = JobSpec.model_validate({**ROOM_SPEC, "up": (0.009, -0.904, -0.427)})
    with detect.captures_kept():
        plan_job(tmp_path / "kept", [kitchen], spec, hand_over=True)
    assert len(reads) == 1
    plan_job(tmp_path / "each", [kitchen], spec, hand_over=True)
    assert len(reads) > 3  # outside it, each step reads the capture again

    inside: list[int] = []  # and generate runs its steps inside it
    monkeypatch.setattr(generate_cli, "_checked_run", lambda *a: inside.append(detect._keeping) or 0)
    argv = ["generate", str(kitchen), "--out", str(tmp_path / "out"), "--workers", "1"]
    args = build_parser(argv).parse_args(argv)
    assert generate_cli.run(args) == 0 and inside == [1] and detect._keeping == 0
