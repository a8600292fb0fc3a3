"""The confined loader (issue 19): names resolved inside the mesh's real folder only, whatever loads the scan
(the worker's own load of a stored space included); texture sizes by header; one compression rule at upload,
packing and extraction; links in the folder store; temp folders of killed processes swept."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import pytest
import trimesh

from services.core.db.models import Space
from services.core.ingest.errors import SpaceError
from services.core.ingest.guard import archive_rules
from services.core.ingest.guard.archive import safe_extract_zip
from services.core.ingest.guard.archive_rules import (
    archive_refusal,
    expansion_refusal,
    file_expansion_refusal,
)
from services.core.ingest.guard.confine import ConfinedResolver, ReferenceRefused
from services.core.ingest.guard.texture_limits import MAX_TEXTURE_SIDE, texture_refusal
from services.core.ingest.loading import load_space
from services.core.ingest.registry import fetch_space
from services.core.storage import LocalStore, ObjectNotFoundError
from services.core.temp_dirs import owned_prefix, sweep_orphans
from tests.fixtures.file_watch import OpenWatch
from tests.fixtures.hostile_corpus import HOSTILE_FILES, UV_FACES, png_declaring, secret_files


def test_resolver_serves_inside_and_refuses_everything_else(tmp_path: Path) -> None:
    secrets = secret_files()
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.png").write_bytes(b"inside")
    (tmp_path / "link.png").symlink_to(secrets["png"])
    resolver = ConfinedResolver(tmp_path / "scan.obj")
    assert resolver.get("sub/a.png") == b"inside" and resolver.get("sub/../sub/a.png") == b"inside"
    with OpenWatch(secrets.values()) as watch:
        for name in (
            str(secrets["png"]), "../" * 20 + str(secrets["png"]).lstrip("/"), "link.png",
            "%2e%2e/" * 20 + str(secrets["png"]).lstrip("/"), f"file://{secrets['png']}", "C:\\x.png",
        ):
            with pytest.raises(ReferenceRefused):
                resolver.get(name)
        with pytest.raises(FileNotFoundError):
            resolver.get("missing.png")
        assert watch.opened() == []
    assert len(resolver.log.refused) == 6 and resolver.refusal() is not None


def _store_space(store: LocalStore, tmp_path: Path, case: str) -> Space:
    """A stored space whose source is a hostile zip, as if it had been registered before the checks
    existed."""
    filename, make, _ = HOSTILE_FILES[case]
    path = tmp_path / filename
    path.write_bytes(make())
    key = f"spaces/1/{filename}"
    store.put_file(key, path)
    return Space(id=1, owner="t", name="s", source_key=key, checksum=case, source_format="zip")


@pytest.mark.parametrize("case", ["obj_comment_mtllib_absolute_texture", "obj_comment_mtllib_dotdot_texture",
                                  "gltf_image_percent_dotdot", "texture_30000_png_behind_comment"])
def test_the_workers_own_load_of_a_stored_space_is_confined(
    tmp_path: Path, local_store: LocalStore, case: str
) -> None:
    space = _store_space(local_store, tmp_path, case)
    with OpenWatch(secret_files().values()) as watch:
        path = fetch_space(local_store, space, tmp_path / "cache")  # what the worker and the planner do
        with pytest.raises(SpaceError):
            load_space(path, unit_scale=1.0)
        assert watch.opened() == []


def test_texture_limit_is_by_declared_size(tmp_path: Path) -> None:
    side = MAX_TEXTURE_SIDE
    assert texture_refusal("t.png", png_declaring(side, side)) is None
    assert "more than the limit" in (texture_refusal("t.png", png_declaring(side + 1, side)) or "")
    assert "more than the limit" in (texture_refusal("t.png", png_declaring(30000, 30000)) or "")
    assert texture_refusal("scan.mtl", b"newmtl m\n") is None  # not an image: not judged


def test_one_compression_rule_for_upload_packing_and_extraction(tmp_path: Path) -> None:
    line = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 300_000
    obj = tmp_path / "rep.obj"
    obj.write_bytes(line)
    packed = tmp_path / "rep.zip"
    with zipfile.ZipFile(packed, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.write(obj, "rep.obj")
    # the file check predicts what the packed zip's check and its extraction say
    assert file_expansion_refusal(obj) is not None and archive_refusal(packed) is not None
    with pytest.raises(SpaceError, match="expands"):
        safe_extract_zip(packed, tmp_path / "x")
    with pytest.raises(SpaceError, match="expands"):
        load_space(obj, unit_scale=1.0)
    # a real scan passes all three, and the file check stops after a fraction of the file
    bunny = trimesh.creation.icosphere(subdivisions=6).export(file_type="obj").encode()
    ok = tmp_path / "ok.obj"
    ok.write_bytes(bunny)
    with zipfile.ZipFile(tmp_path / "ok.zip", "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.write(ok, "ok.obj")
    assert file_expansion_refusal(ok) is None and archive_refusal(tmp_path / "ok.zip") is None


@pytest.mark.parametrize("period", [1, 100])
def test_file_expansion_verdict_is_the_whole_files_whatever_the_piece_size(
    tmp_path: Path, period: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # period 1: one repeated face line (680x); 100: just over the limit at level 6 (203x), far under it at
    # level 1
    body = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"".join(b"f 1 2 %d\n" % (3 + i % period) for i in range(300_000))
    obj = tmp_path / "near.obj"
    obj.write_bytes(body)
    whole = zlib.compressobj(zlib.Z_DEFAULT_COMPRESSION, zlib.DEFLATED, -15)
    expected = expansion_refusal("the mesh file", len(body), len(whole.compress(body) + whole.flush()))
    # both refused: the check is stricter than the level-1 packed zip (59x for 100)
    assert expected is not None
    for piece in (1 << 12, 1 << 16, 1 << 20, 1 << 24):
        monkeypatch.setattr(archive_rules, "_CHUNK", piece)
        assert file_expansion_refusal(obj) == expected
    # a scan: under the limit after its first pieces, the same verdict for every size
    ok = tmp_path / "ok.obj"
    ok.write_bytes(trimesh.creation.icosphere(subdivisions=6).export(file_type="obj").encode())
    for piece in (1 << 12, 1 << 16, 1 << 24):
        monkeypatch.setattr(archive_rules, "_CHUNK", piece)
        assert file_expansion_refusal(ok) is None


def test_local_store_never_reads_through_a_link(tmp_path: Path) -> None:
    store = LocalStore(tmp_path / "objects")
    secret = secret_files()["png"]
    (store.root / "uploads").mkdir()
    (store.root / "uploads" / "s.png").symlink_to(secret)
    (store.root / "dir").symlink_to(secret.parent, target_is_directory=True)
    with OpenWatch([secret]) as watch:
        for key in ("uploads/s.png", "dir/secret.png"):
            assert store.stat(key) is None and not store.exists(key)
            with pytest.raises(ObjectNotFoundError):
                store.get_bytes(key)
            with pytest.raises(ObjectNotFoundError):
                store.get_file(key, tmp_path / "copy")
        assert watch.opened() == []


def test_sweep_removes_folders_of_dead_owners_only(tmp_path: Path) -> None:
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    dead_pid = int(dead.stdout)
    mine = tmp_path / f"{owned_prefix('upload')}abc"
    theirs = tmp_path / f"{owned_prefix('upload', dead_pid)}abc"
    old_unnamed = tmp_path / "omnidata-upload-xyz"
    other_kind = tmp_path / f"{owned_prefix('plan', dead_pid)}abc"
    for folder in (mine, theirs, old_unnamed, other_kind):
        folder.mkdir()
        (folder / "scan.zip").write_bytes(b"x" * 10)
    os.utime(old_unnamed, (0, 0))
    exr_dead = tmp_path / f"{owned_prefix('exr', dead_pid)}abc.exr"  # a worker killed while encoding
    exr_live = tmp_path / f"{owned_prefix('exr')}abc.exr"
    for f in (exr_dead, exr_live):
        f.write_bytes(b"x")
    removed = sweep_orphans(("upload", "exr"), (tmp_path,))
    assert sorted(removed) == sorted([theirs, old_unnamed, exr_dead])
    assert mine.exists() and other_kind.exists() and not theirs.exists() and exr_live.exists()


def test_a_zombie_owner_counts_as_dead(tmp_path: Path) -> None:
    # a killed process nobody reaps (a container's init may not) stays a zombie: its pid, nothing else
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    deadline = time.monotonic() + 30
    while Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
        assert time.monotonic() < deadline
        time.sleep(0.01)
    folder = tmp_path / f"{owned_prefix('plan', child.pid)}abc"
    folder.mkdir()
    try:
        assert sweep_orphans(("plan",), (tmp_path,)) == [folder] and not folder.exists()
    finally:
        child.wait()


def test_killed_api_leaves_no_upload_folder(tmp_path: Path, pg_url: str) -> None:
    """kill -9 of a process holding an upload folder; the next API start removes it."""
    from tests.fixtures.api import make_api

    child = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; sys.path.insert(0, '.');"
         "from services.core.temp_dirs import owned_temp_dir; d = owned_temp_dir('upload');"
         "open(d.name + '/scan.zip', 'wb').write(b'x' * 1000); print(d.name, flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[4],
    )
    assert child.stdout is not None
    folder = Path(child.stdout.readline().strip())
    assert (folder / "scan.zip").exists()
    child.kill()
    child.wait()
    assert folder.exists()  # kill -9: nothing cleaned
    with make_api(pg_url, LocalStore(tmp_path / "objects")):
        assert not folder.exists()


def test_packing_keeps_the_library_trimesh_reads_behind_a_comment(tmp_path: Path) -> None:
    """What the loader textured at upload is what the stored zip holds, so planning renders the same."""
    from services.core.ingest.guard.archive import resolve_source
    from services.core.ingest.registry import pack_source

    (tmp_path / "scan").mkdir()
    obj = tmp_path / "scan" / "scan.obj"
    obj.write_bytes(b"# mtllib evil.mtl\nusemtl m\n" + UV_FACES)
    (obj.parent / "evil.mtl").write_text("newmtl m\nmap_Kd tex.png\n")
    (obj.parent / "tex.png").write_bytes(png_declaring(4, 4))
    packed = pack_source(obj, resolve_source(obj), tmp_path)
    with zipfile.ZipFile(packed) as zf:
        assert sorted(zf.namelist()) == ["evil.mtl", "scan.obj", "tex.png"]
