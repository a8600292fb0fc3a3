"""The loaded space `omnidata generate` hands to its local workers (services.worker.inputs.loaded_cache, issue
20): read back, it equals a fresh `load_space(source, source_to_world=...)` (what a worker parsed before) in
every array the worker reads; a stale, foreign or damaged file is ignored and the scan is parsed; a worker's
outputs are the same bytes whichever way it got the space."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

import services.worker.run.making as making_mod
from services.core.db.jobs import job_spaces
from services.core.db.models import Job
from services.core.ingest.loading import LoadedSpace, load_space
from services.worker.inputs.loaded_cache import keep_loaded, loaded_path, read_loaded
from tests.fixtures.scenes import write_ply_with_labels
from tests.worker.run.test_runner import banana, make_job, runner, sm
from tests.worker.run.test_view_batch import outputs, queue_view, render

__all__ = ["banana", "sm"]  # fixtures used by name

CHECKSUM = "ab" * 32


def _coloured(tmp: Path, kind: str) -> Path:
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    rng = np.random.default_rng(0)
    if kind == "vertex":
        box.visual.vertex_colors = rng.integers(0, 255, (len(box.vertices), 4), dtype=np.uint8)
    else:
        box.visual.face_colors = rng.integers(0, 255, (len(box.faces), 4), dtype=np.uint8)
    path = tmp / f"{kind}.ply"
    box.export(path)
    return path


def _labelled(tmp: Path) -> Path:
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0))
    path = tmp / "labelled.ply"
    nf = len(box.faces)
    write_ply_with_labels(
        path, np.asarray(box.vertices), box.faces.tolist(), np.arange(nf) % 3, np.arange(nf) % 5
    )
    return path


def source(name: str, scenes_dir: Path, tmp: Path) -> Path:
    return {
        "banana": lambda: scenes_dir / "ycb_banana",  # a texture image
        "icl": lambda: scenes_dir / "icl_livingroom",  # UVs, no image: the material's colour
        "bunny": lambda: scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply",  # no colour
        "vertex": lambda: _coloured(tmp, "vertex"),
        "face": lambda: _coloured(tmp, "face"),
        "labelled": lambda: _labelled(tmp),
    }[name]()


def frame_of(loaded: LoadedSpace) -> dict[str, Any]:
    """The frame a worker loads a planned space in: its planner's source_to_world, through JSON."""
    return {"source_to_world": json.loads(json.dumps(loaded.source_to_world.tolist()))}


@pytest.mark.parametrize("name", ["banana", "icl", "bunny", "vertex", "face", "labelled"])
def test_the_kept_space_equals_a_fresh_load_in_its_frame(name: str, scenes_dir: Path, tmp_path: Path) -> None:
    path = source(name, scenes_dir, tmp_path)
    loaded = load_space(path)
    # what the parent computed before does not travel (normals differ by the frame)
    _ = loaded.mesh.face_normals
    assert keep_loaded(tmp_path / "cache", CHECKSUM, loaded) is not None
    frame = frame_of(loaded)
    got = read_loaded(tmp_path / "cache", CHECKSUM, frame)
    fresh = load_space(path, **frame)
    assert got is not None
    a, b = fresh.mesh, got.mesh
    assert not {"vertex_normals", "face_normals"} & set(b._cache.cache)
    for attr in ("vertices", "faces", "vertex_normals", "face_normals", "area_faces", "triangles"):
        x, y = getattr(a, attr), getattr(b, attr)
        assert x.dtype == y.dtype and np.array_equal(x, y), attr
    assert a.visual.kind == b.visual.kind
    if a.visual.kind == "texture":
        assert np.array_equal(a.visual.uv, b.visual.uv)
        assert np.array_equal(a.visual.material.main_color, b.visual.material.main_color)
        ia, ib = a.visual.material.image, b.visual.material.image
        assert (ia is None) == (ib is None) == (name != "banana")
        if ia is not None:
            assert ia.mode == ib.mode and np.array_equal(np.asarray(ia), np.asarray(ib))
    elif a.visual.kind == "vertex":
        assert np.array_equal(a.visual.vertex_colors, b.visual.vertex_colors)
    elif a.visual.kind == "face":
        assert np.array_equal(a.visual.face_colors, b.visual.face_colors)
    for attr in ("face_class", "face_instance"):
        x, y = getattr(fresh, attr), getattr(got, attr)
        assert (x is None and y is None) or (x.dtype == y.dtype and np.array_equal(x, y)), attr
    assert (fresh.face_class is not None) == (name == "labelled")


def _damage(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "flipped":
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    elif how == "truncated":
        path.write_bytes(bytes(data[: len(data) // 2]))
    elif how == "garbage":
        path.write_bytes(b"not a zip")
    elif how == "moved vertex":  # a valid npz whose content does not match its digest
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["vertices"] = arrays["vertices"].copy()
        arrays["vertices"][0, 0] += 1e-3
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
    elif how == "pickled":  # an object array: never unpickled
        with open(path, "wb") as fh:
            np.savez(fh, vertices=np.array([object()], dtype=object))


@pytest.mark.parametrize("how", ["flipped", "truncated", "garbage", "moved vertex", "pickled"])
def test_a_damaged_file_is_not_used(how: str, scenes_dir: Path, tmp_path: Path) -> None:
    loaded = load_space(scenes_dir / "ycb_banana")
    path = keep_loaded(tmp_path, CHECKSUM, loaded)
    assert path is not None
    _damage(path, how)
    assert read_loaded(tmp_path, CHECKSUM, frame_of(loaded)) is None


def test_another_frame_source_or_request_is_not_used(scenes_dir: Path, tmp_path: Path) -> None:
    loaded = load_space(scenes_dir / "ycb_banana")
    path = keep_loaded(tmp_path, CHECKSUM, loaded)
    assert path is not None
    frame = frame_of(loaded)
    assert read_loaded(tmp_path, CHECKSUM, frame) is not None
    moved = np.array(frame["source_to_world"])
    moved[0, 3] += 1e-9
    assert read_loaded(tmp_path, CHECKSUM, {"source_to_world": moved.tolist()}) is None  # another frame
    assert read_loaded(tmp_path, "cd" * 32, frame) is None  # another source
    assert read_loaded(tmp_path, CHECKSUM, {"up_axis": "z", "unit_scale": 1.0}) is None  # not a planned frame
    other = loaded_path(tmp_path, "cd" * 32, moved)  # a file named for another source holds this one: refused
    other.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(path, other)
    assert read_loaded(tmp_path, "cd" * 32, {"source_to_world": moved.tolist()}) is None


@pytest.mark.parametrize("sm", ["sqlite"], indirect=True)
def test_a_worker_renders_the_same_bytes_from_the_kept_space_and_from_the_scan(
    sm, banana, scenes_dir, tmp_path, monkeypatch
):
    loads: list[str] = []
    real_load = making_mod.load_space

    def counting(path: Any, **kw: Any) -> Any:
        loads.append(str(path))
        return real_load(path, **kw)

    monkeypatch.setattr(making_mod, "load_space", counting)
    loaded = load_space(scenes_dir / "ycb_banana")  # the banana fixture's frame: auto, as its plan was made
    frame = loaded.source_to_world.tolist()

    def run_view() -> dict[str, bytes]:
        job_id = make_job(sm, banana)
        with sm() as s:  # the planner's record of the frame: what a worker loads the space in
            job = s.get(Job, job_id)
            assert job is not None
            ((_js, space),) = job_spaces(s, job_id)
            job.plan_summary = {"spaces": {space.name: {"source_to_world": frame}}}
            s.commit()
        render(sm, banana, job_id)  # a fresh runner (no space in memory from the run before) renders the view
        r = runner(sm, banana, "w1")  # and another derives its cues from the stored pass set
        tids = queue_view(sm, job_id, 0, 0)
        r.run(next(iter(tids.values())))
        return outputs(sm, banana, tids)

    checksum = banana.space_fields["checksum"]
    kept = loaded_path(banana.cache_dir, checksum, loaded.source_to_world)
    kept.unlink(missing_ok=True)
    parsed = run_view()
    assert len(loads) == 1
    assert keep_loaded(banana.cache_dir, checksum, loaded) == kept
    assert run_view() == parsed
    assert len(loads) == 1  # read from the cache: no parse
    _damage(kept, "flipped")
    assert run_view() == parsed
    assert len(loads) == 2  # the damaged file was ignored
    kept.unlink()
