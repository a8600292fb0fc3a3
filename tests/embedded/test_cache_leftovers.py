"""Temporary files that writers killed before their rename left in the caches (services.core.user_cache.
remove_stale_temps): readers never use them, and pruning a folder removes them once old enough that no live
writer can own them, while a young one (a write in flight) and the finished entries stay."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import services.worker.inputs.curvature as estimator
from services.core.ingest.loading import load_space
from services.core.ingest.parsed_cache import load_space_kept
from services.core.ingest.pointcloud import Cloud, mesh_cloud_cached
from services.core.ingest.registry import source_checksum
from services.core.user_cache import (
    CURVATURE,
    LOADED,
    MESHED,
    PARSED,
    PRUNED,
    STALE_TEMP_S,
    TEMP_PREFIX,
    prune_user_caches,
)
from services.worker.inputs.loaded_cache import keep_loaded, loaded_path, read_loaded
from services.worker.inputs.shared_curvature import shared_curvature
from tests.conftest import REPO_ROOT
from tests.worker.inputs.test_shared_curvature import RADIUS, room_like

FRAME = {"up_axis": "+z", "unit_scale": 1.0}
UNLIMITED = 2**40


def bunny(scenes_dir: Path) -> Path:
    return scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"


def set_back(path: Path, seconds: float) -> None:
    st = path.stat()
    os.utime(path, (st.st_atime - seconds, st.st_mtime - seconds))


def leftover(folder: Path, name: str, age_s: float) -> Path:
    """A temporary file as the `name` folder's writer makes it, last written `age_s` ago."""
    fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX[name], dir=folder)
    os.write(fd, b"half an entry")
    os.close(fd)
    set_back(Path(tmp), age_s)
    return Path(tmp)


def state(folder: Path) -> dict[str, tuple[int, float]]:
    """name -> (inode, mtime) of every file: a rewrite changes the inode, a touch the mtime."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime) for p in folder.iterdir()}


def test_pruning_removes_old_leftovers_of_every_user_cache_and_keeps_young_ones_and_entries(
    scenes_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    user = tmp_path / "user"
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(user))
    scan = bunny(scenes_dir)
    load_space_kept(scan, source_checksum(scan), FRAME)
    shared_curvature(room_like(), RADIUS, user / CURVATURE)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 2, 3000), rng.uniform(0, 2, 3000), np.zeros(3000)])
    mesh_cloud_cached(lambda: Cloud(pts, None, None), "0" * 64, "cloud", user / MESHED)
    old, young, entries = [], [], {}
    for name in (MESHED, PARSED, CURVATURE):
        folder = user / name
        for p in folder.iterdir():
            set_back(p, 30 * 86400)  # finished entries used long ago: still within the limit, so kept
        entries[name] = state(folder)
        old.append(leftover(folder, name, STALE_TEMP_S + 60))
        young.append(leftover(folder, name, 60))
    prune_user_caches(UNLIMITED)
    assert not any(p.exists() for p in old)
    assert all(p.exists() for p in young)
    for name in (MESHED, PARSED, CURVATURE):
        after = state(user / name)
        assert set(after) == set(entries[name]) | {p.name for p in young if p.parent.name == name}
        assert {entry: after[entry] for entry in entries[name]} == entries[name]  # untouched


def test_writing_a_loaded_space_removes_old_leftovers_of_its_folder(scenes_dir: Path, tmp_path: Path) -> None:
    scan = bunny(scenes_dir)
    loaded, checksum = load_space(scan, **FRAME), source_checksum(scan)
    folder = tmp_path / LOADED
    folder.mkdir()
    old, young = leftover(folder, LOADED, STALE_TEMP_S + 60), leftover(folder, LOADED, 60)
    path = keep_loaded(tmp_path, checksum, loaded)
    assert path == loaded_path(tmp_path, checksum, loaded.source_to_world) and path.is_file()
    assert not old.exists() and young.exists()


# Runs one cache writer and stops it for good between its temporary file and the rename (the hook prints the
# file's path and waits): the parent then kills it, as kill -9 or the OOM killer would.
WRITER = r"""
import os, sys, time
from pathlib import Path

def hold(src, dst):
    print(src, flush=True)
    time.sleep(600)

os.replace = hold
which, scan, folder = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
if which == "curvature":
    from services.worker.inputs.shared_curvature import shared_curvature
    from tests.worker.inputs.test_shared_curvature import RADIUS, room_like
    shared_curvature(room_like(), RADIUS, folder)
elif which == "parsed":
    from services.core.ingest.parsed_cache import load_space_kept
    from services.core.ingest.registry import source_checksum
    load_space_kept(scan, source_checksum(scan), {"up_axis": "+z", "unit_scale": 1.0}, folder)
else:
    from services.core.ingest.loading import load_space
    from services.core.ingest.registry import source_checksum
    from services.worker.inputs.loaded_cache import keep_loaded
    keep_loaded(folder, source_checksum(scan), load_space(scan, up_axis="+z", unit_scale=1.0))
"""


def killed_mid_write(which: str, scan: Path, folder: Path) -> Path:
    """Start the writer of `which`, SIGKILL it once its temporary file is written; that file."""
    proc = subprocess.Popen([sys.executable, "-c", WRITER, which, str(scan), str(folder)], cwd=REPO_ROOT,
                            env={**os.environ, "PYTHONPATH": str(REPO_ROOT)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 300)
        line = proc.stdout.readline().strip() if ready else ""
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert line, f"the writer never reached its rename: {err[-2000:]}"
    return Path(line)


def use(which: str, scan: Path, folder: Path) -> bytes:
    """What the cache `which` gives (computed when nothing usable is kept), as bytes to compare."""
    if which == CURVATURE:
        return shared_curvature(room_like(), RADIUS, folder).tobytes()
    return load_space_kept(scan, source_checksum(scan), FRAME, folder).mesh.vertices.tobytes()


@pytest.mark.parametrize("which", [CURVATURE, PARSED])
def test_a_user_cache_writer_killed_mid_write_leaves_a_file_readers_ignore_and_pruning_removes(
    which: str, scenes_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    user = tmp_path / "user"
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(user))
    folder, scan = user / which, bunny(scenes_dir)
    tmp = killed_mid_write(which, scan, folder)
    assert tmp.parent == folder and tmp.name.startswith(TEMP_PREFIX[which]) and tmp.stat().st_size > 0
    assert [p for p in folder.glob(f"*{PRUNED[which]}") if p != tmp] == []  # never renamed into place

    if which == CURVATURE:
        direct = estimator.principal_curvatures(room_like(), RADIUS).tobytes()
    else:
        direct = load_space(scan, **FRAME).mesh.vertices.tobytes()
    assert use(which, scan, folder) == direct  # the leftover is no entry (and the killed writer's lock died)
    (entry,) = (p for p in folder.glob(f"*{PRUNED[which]}") if p != tmp)
    kept = state(folder)
    prune_user_caches(UNLIMITED)
    assert tmp.exists()  # young: it could be a live writer's
    set_back(tmp, STALE_TEMP_S + 60)
    prune_user_caches(UNLIMITED)
    assert not tmp.exists()
    assert state(folder) == {name: v for name, v in kept.items() if name != tmp.name}
    assert use(which, scan, folder) == direct
    assert entry.stat().st_ino == kept[entry.name][0]  # read back, not written again


def test_a_loaded_space_writer_killed_mid_write_leaves_a_file_readers_ignore_and_the_next_write_removes(
    scenes_dir: Path, tmp_path: Path,
) -> None:
    scan = bunny(scenes_dir)
    tmp = killed_mid_write("loaded", scan, tmp_path)
    assert tmp.parent == tmp_path / LOADED and tmp.name.startswith(TEMP_PREFIX[LOADED])
    loaded, checksum = load_space(scan, **FRAME), source_checksum(scan)
    frame = {"source_to_world": loaded.source_to_world}
    assert read_loaded(tmp_path, checksum, frame) is None  # nothing kept: the scan is parsed
    keep_loaded(tmp_path, checksum, loaded)
    assert tmp.exists()  # young: it could be a live writer's
    back = read_loaded(tmp_path, checksum, frame)
    assert back is not None and np.array_equal(back.mesh.vertices, loaded.mesh.vertices)
    set_back(tmp, STALE_TEMP_S + 60)
    keep_loaded(tmp_path, checksum, loaded)
    assert not tmp.exists()
    entry = loaded_path(tmp_path, checksum, loaded.source_to_world)
    assert [p.name for p in (tmp_path / LOADED).iterdir()] == [entry.name]
