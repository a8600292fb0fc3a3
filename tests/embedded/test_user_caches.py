"""The user's caches that outlive a run (services.core.user_cache): a packed source, a parsed space and the
per-vertex curvature that a second `omnidata generate` on the same scan reads back, keyed so that a changed
file or frame misses, a damaged entry replaced, and the folders kept under their size limit."""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.core.domain.jobspec import JobSpec
from services.core.ingest import registry
from services.core.ingest.loading import LoadedSpace, load_space
from services.core.ingest.parsed_cache import SUFFIX, load_space_kept, parsed_key
from services.core.ingest.pointcloud import Cloud, mesh_cloud_cached
from services.core.ingest.registry import source_checksum
from services.core.user_cache import MESHED, PRUNED, evict_oldest
from tests.fixtures.cli import dataset_files, omnidata


def same_space(a: LoadedSpace, b: LoadedSpace) -> None:
    for name in ("vertices", "faces", "vertex_normals"):
        assert np.array_equal(getattr(a.mesh, name), getattr(b.mesh, name)), name
    assert np.array_equal(a.source_to_world, b.source_to_world) and np.array_equal(a.bounds, b.bounds)
    assert a.frame_record() == b.frame_record() and a.checksum == b.checksum


def same_values(a: Any, b: Any, where: str) -> None:
    """Every field, item and array of `a` is `b`'s, bit for bit (nested dataclasses, tuples, dicts)."""
    assert type(a) is type(b), where
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            same_values(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, (tuple, list, dict)):
        assert len(a) == len(b), where
        pairs = zip(a.values(), b.values(), strict=True) if isinstance(a, dict) else zip(a, b, strict=True)
        for i, (x, y) in enumerate(pairs):
            same_values(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), where
    else:
        assert a == b or (a != a and b != b), where  # NaN is NaN


def entries(folder: Path, suffix: str) -> dict[str, tuple[int, float]]:
    """name -> (inode, mtime): a rewrite (tmp + os.replace) changes the inode, a hit only the mtime."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime) for p in sorted(folder.glob(f"*{suffix}"))}


def age(folder: Path, seconds: float = 3600) -> None:
    for p in folder.iterdir():
        st = p.stat()
        os.utime(p, (st.st_atime - seconds, st.st_mtime - seconds))


# the curvature cue and one it is made with, on few small views
SPEC = """
cues: [principal_curvature, normal]
cameras: {mode: object, object_count: 6}
points: {count: 1, min_views: 2, max_views: 2}
views: {resolution: 32}
"""


@pytest.mark.bpy
def test_a_second_run_reads_both_caches_and_writes_the_same_files(scenes_dir: Path, tmp_path: Path) -> None:
    user = tmp_path / "user"
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)
    outs = []
    for run in ("first", "second"):
        out = tmp_path / run
        res = omnidata("generate", scenes_dir / "ycb_banana", "--out", out, "--spec", spec, "--seed", 3,
                       "--workers", 1, "--name", "demo", "--no-progress",
                       env={"OMNIDATA_DATA_DIR": str(user)})
        assert res.returncode == 0, res.stderr
        outs.append(out)
        if run == "first":
            parsed, curvature = entries(user / "parsed", SUFFIX), entries(user / "curvature", ".npy")
            assert len(parsed) == 1 and len(curvature) == 1
            age(user / "parsed")
            age(user / "curvature")
            aged = entries(user / "parsed", SUFFIX), entries(user / "curvature", ".npy")
    for before, after in zip(aged, (entries(user / "parsed", SUFFIX), entries(user / "curvature", ".npy")),
                             strict=True):
        assert before.keys() == after.keys()
        for name, (inode, mtime) in after.items():
            assert inode == before[name][0]  # not written again
            assert mtime > before[name][1] + 1800  # read: a hit marks its entry used
    files = dataset_files(outs[0])
    assert any(name.startswith("principal_curvature/") for name in files)
    assert files == dataset_files(outs[1])


def test_a_room_read_back_is_the_room_loaded(scenes_dir: Path, tmp_path: Path) -> None:
    """The ICL living room: a texture, and up and units detected (the evidence is kept too)."""
    room = scenes_dir / "icl_livingroom"
    checksum = source_checksum(room)
    frame = JobSpec().space_frame()
    load_space_kept(room, checksum, frame, tmp_path)
    (entry,) = tmp_path.glob(f"*{SUFFIX}")
    age(tmp_path)
    kept, loaded = load_space_kept(room, checksum, frame, tmp_path), load_space(room, **frame)
    assert entry.stat().st_mtime > time.time() - 1800  # read back
    same_space(kept, loaded)
    for evidence in ("up_estimate", "units", "capture", "warnings", "class_names"):
        same_values(getattr(kept, evidence), getattr(loaded, evidence), evidence)
    assert np.array_equal(kept.mesh.visual.uv, loaded.mesh.visual.uv)
    assert np.array_equal(np.asarray(kept.mesh.visual.material.image),
                          np.asarray(loaded.mesh.visual.material.image))


def test_a_changed_file_or_frame_misses_and_a_damaged_entry_is_replaced(scenes_dir: Path, tmp_path: Path,
                                                                         ) -> None:
    scan = tmp_path / "bunny.ply"
    shutil.copy(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply", scan)
    folder = tmp_path / "parsed"
    frame = {"up_axis": "+z", "unit_scale": 1.0}
    checksum = source_checksum(scan)
    first = load_space_kept(scan, checksum, frame, folder)
    assert len(entries(folder, SUFFIX)) == 1
    age(folder)
    kept = entries(folder, SUFFIX)
    again = load_space_kept(scan, checksum, frame, folder)
    same_space(again, first)
    assert entries(folder, SUFFIX).keys() == kept.keys() and entries(folder, SUFFIX) != kept  # a hit

    other_frame = {"up_axis": "+y", "unit_scale": 1.0}
    turned = load_space_kept(scan, checksum, other_frame, folder)
    same_space(turned, load_space(scan, **other_frame))
    assert len(entries(folder, SUFFIX)) == 2

    scan.write_bytes(scan.read_bytes().replace(b"end_header", b"comment changed\nend_header", 1))
    changed = source_checksum(scan)
    assert changed != checksum
    load_space_kept(scan, changed, frame, folder)
    assert len(entries(folder, SUFFIX)) == 3

    entry = folder / f"{parsed_key(changed, scan, frame)}{SUFFIX}"
    data = entry.read_bytes()
    entry.write_bytes(data[:-10] + b"0123456789")  # damaged: its digest no longer fits
    damaged = entry.stat().st_ino
    same_space(load_space_kept(scan, changed, frame, folder), load_space(scan, **frame))
    assert entry.stat().st_ino != damaged and entry.read_bytes() == data  # written again


def test_a_packed_source_is_zipped_once_and_a_changed_or_damaged_one_zipped_again(
        scenes_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An OBJ with its material (stored as their zip): its checksum read back from the user's packed folder,
    the same bytes, until one of its files is written; a damaged entry is zipped again."""
    room = tmp_path / "room"
    shutil.copytree(scenes_dir / "icl_livingroom", room)
    user = tmp_path / "user"
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(user))
    first = source_checksum(room)
    (entry,) = (user / "packed").glob("*.zip")
    age(user / "packed")
    registry._PACKED.clear()  # what this process zipped: as in the next run

    def no_zipping(*args: object, **kwargs: object) -> None:
        raise AssertionError("zipped again")

    with monkeypatch.context() as m:
        m.setattr(registry, "_write_zip", no_zipping)
        assert source_checksum(room) == first  # the zip read back: the same bytes
    assert entry.stat().st_mtime > time.time() - 1800  # a hit marks its entry used

    mtl = room / "livingroom.mtl"
    mtl.write_text(mtl.read_text() + "# changed\n")
    registry._PACKED.clear()
    changed = source_checksum(room)
    assert changed != first and len(list((user / "packed").glob("*.zip"))) == 2

    (kept,) = [p for p in (user / "packed").glob("*.zip") if p != entry]
    data = kept.read_bytes()
    kept.write_bytes(data[:-10] + b"0123456789")  # damaged: its digest no longer fits
    registry._PACKED.clear()
    assert source_checksum(room) == changed
    assert kept.read_bytes() == data  # written again

    mtl.write_text(mtl.read_text() + "# changed again\n")
    (tmp_path / "upload").mkdir()
    registry.pack_source(room, room / "livingroom.obj", tmp_path / "upload")  # the API's register: not kept
    assert len(list((user / "packed").glob("*.zip"))) == 2


def test_a_folder_in_the_way_falls_back_to_loading(scenes_dir: Path, tmp_path: Path) -> None:
    scan = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    frame = {"up_axis": "+z", "unit_scale": 1.0}
    same_space(load_space_kept(scan, "c" * 64, frame, blocked / "parsed"), load_space(scan, **frame))


def test_the_folders_are_pruned_to_their_limit_oldest_first(tmp_path: Path) -> None:
    folder = tmp_path / "curvature"
    folder.mkdir()
    for i in range(4):
        p = folder / f"{i}.npy"
        p.write_bytes(b"x" * 100)
        os.utime(p, (1000 + i, 1000 + i))
        (folder / f"{i}.lock").touch()
    (folder / ".curvature-tmp.npy").write_bytes(b"x" * 100)  # a write in flight: not counted, kept
    evict_oldest(folder, 250, ".npy")
    assert sorted(p.name for p in folder.iterdir()) == [".curvature-tmp.npy", "2.lock", "2.npy", "3.lock",
                                                         "3.npy"]
    assert evict_oldest(tmp_path / "none", 0, ".npy") == []


def test_a_meshed_cloud_is_pruned_with_its_record_and_a_hit_keeps_it(tmp_path: Path) -> None:
    folder = tmp_path / "meshed"
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 2, 3000), rng.uniform(0, 2, 3000), np.zeros(3000)])
    clouds = [Cloud(pts + [0, 0, i], None, None) for i in range(2)]
    plys = []
    for i, cloud in enumerate(clouds):
        mesh_cloud_cached(lambda c=cloud: c, f"{i}" * 64, f"cloud {i}", folder)
        plys.append(next(p for p in folder.glob("*.ply") if p not in plys))
        os.utime(plys[-1], (1000 + i, 1000 + i))  # the first cloud's mesh used longest ago
    mesh_cloud_cached(lambda: clouds[0], "0" * 64, "cloud 0", folder)  # a hit: now the most recent
    evict_oldest(folder, plys[0].stat().st_size, PRUNED[MESHED])
    kept = sorted([plys[0].name, plys[0].with_suffix(".json").name])
    assert sorted(p.name for p in folder.iterdir()) == kept


def test_nothing_is_pruned_under_the_limit(tmp_path: Path) -> None:
    (tmp_path / "a.space").write_bytes(b"x")
    assert evict_oldest(tmp_path, 1, SUFFIX) == []
    assert [p.name for p in evict_oldest(tmp_path, 0, SUFFIX)] == ["a.space"]
