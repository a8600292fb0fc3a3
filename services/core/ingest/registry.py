"""Registering spaces in object storage and fetching them back for planning and rendering.

A space's source is stored as ONE object under `<key_prefix>/<space id>/<file>`: a .ply/.glb/.zip as
given, or a zip of the files a mesh needs (an .obj with its .mtl and textures, a .gltf with its buffers
and images, or a whole folder). Validation happens before anything is stored, so a refused upload
leaves no row and no object.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Unpack

from sqlalchemy.orm import Session

from services.core.db.models import Space
from services.core.domain.jobspec import SpaceFrame
from services.core.domain.keys import check_name
from services.core.ingest import packed_cache
from services.core.ingest.datasets import DatasetError, scene_mesh_in, scene_of
from services.core.ingest.errors import SpaceError
from services.core.ingest.formats import scannet_companions
from services.core.ingest.frame.recorded_gravity import recorded_gravity_files
from services.core.ingest.guard.archive import resolve_source
from services.core.ingest.guard.archive_rules import archive_refusal
from services.core.ingest.guard.confine import is_inside, read_confined, real_folder
from services.core.ingest.loading import LoadedSpace, load_space
from services.core.storage.base import ObjectStore, sha256_file
from services.core.temp_dirs import owned_temp_dir

SINGLE_FILE_SUFFIXES = {".ply", ".glb", ".stl", ".off", ".zip", ".xyz", ".pts"}
MAX_PACKED_BYTES = 4 << 30
# A source's zip stores members that are compressed already (photos, depth PNGs, textures) and deflates the
# rest at level 1: on the 7-Scenes kitchen (a 7.7 MB PLY and 200 frames) deflating the frames saved 12 KB of
# 16 MB for 0.23 CPU-s, and level 6 saved 1% more than level 1 for 0.18 CPU-s, paid on every `generate` (its
# checksum).
STORED_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".webp", ".ktx2", ".zip", ".gz"})
PACK_DEFLATE_LEVEL = 1
# what a zip's bytes depend on besides its files: an earlier run's zip (packed_cache) is reused under these
PACKER = (PACK_DEFLATE_LEVEL, tuple(sorted(STORED_SUFFIXES)), zlib.ZLIB_RUNTIME_VERSION)


def _obj_companions(obj: Path) -> list[Path]:
    """The .mtl files an .obj names and the texture maps those name (relative paths only)."""
    out: list[Path] = []
    mtl_re = re.compile(r"^\s*mtllib\s+(.+?)\s*$")
    map_re = re.compile(r"^\s*(map_\w+|bump|disp|decal|norm)\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$", re.IGNORECASE)
    mtls: list[str] = []
    with open(obj, errors="replace") as f:
        for line in f:
            if not mtls and "mtllib" in line:  # trimesh reads the first 'mtllib' anywhere (a comment, a name)
                mtls.append(line[line.index("mtllib") + len("mtllib"):].strip())
            if m := mtl_re.match(line):
                mtls.append(m.group(1))
    root = real_folder(obj)
    for name in dict.fromkeys(n for n in mtls if n):
        mtl = obj.parent / name
        # never read (nor pack) a file outside the scan's folder
        if not mtl.is_file() or not is_inside(mtl, root):
            continue
        out.append(mtl)
        for line in read_confined(mtl, obj).decode("utf-8", "replace").splitlines():
            if m := map_re.match(line):
                tex = mtl.parent / m.group(2)
                if tex.is_file():
                    out.append(tex)
    return out


def _gltf_companions(gltf: Path) -> list[Path]:
    """Buffers and images a .gltf references by relative URI."""
    try:
        doc = json.loads(read_confined(gltf, gltf))
    except (OSError, ValueError) as e:
        raise SpaceError(f"{gltf.name}: not valid glTF JSON ({e})") from None
    uris = [b.get("uri") for b in doc.get("buffers", [])] + [i.get("uri") for i in doc.get("images", [])]
    return [gltf.parent / u for u in uris if u and not u.startswith("data:") and (gltf.parent / u).is_file()]


def _dataset_pack(source: Path) -> tuple[Path, list[Path]] | None:
    """(base folder, files) of a public dataset's scene (a scene folder or its mesh file): what it needs,
    not its raw captures (e.g. ScanNet's .sens); None when `source` is not one."""
    mesh = scene_mesh_in(source) if source.is_dir() else source
    try:
        scene = scene_of(mesh) if mesh is not None else None
    except DatasetError as e:
        raise SpaceError(str(e)) from None
    if scene is None:
        return None
    from services.core.ingest.capture.attach import capture_files_beside
    from services.core.ingest.guard.archive import MESH_SUFFIXES

    extra = _obj_companions(scene.mesh) if scene.mesh.suffix.lower() == ".obj" else []
    capture = capture_files_beside(scene.mesh, MESH_SUFFIXES)  # a posed capture beside the scan goes along
    files = list(dict.fromkeys([*scene.files, *extra, *capture]))
    base = source if source.is_dir() else Path(os.path.commonpath([f.parent for f in files]))
    root = Path(os.path.realpath(base))  # no file whose real path leaves the scene (a link out of it)
    return base, [f for f in files if not f.is_symlink() and is_inside(f, root)]


def _files_to_pack(source: Path, mesh_file: Path) -> tuple[Path, list[Path]]:
    """(base folder, files) that a mesh needs, for zipping (with a posed capture beside it: the capture
    too)."""
    from services.core.ingest.capture.attach import capture_files_beside
    from services.core.ingest.guard.archive import MESH_SUFFIXES

    if (dataset := _dataset_pack(source)) is not None:
        return dataset
    beside = capture_files_beside(mesh_file, MESH_SUFFIXES) if source.is_file() else []
    if beside:
        return mesh_file.parent, beside
    if source.is_dir():
        files = [p for p in sorted(source.rglob("*")) if p.is_file() and not p.is_symlink()]
        return source, files
    scannet = scannet_companions(mesh_file)
    if scannet is not None:  # a ScanNet mesh keeps its label files
        companions = list(scannet)
    elif mesh_file.suffix.lower() == ".obj":
        companions = _obj_companions(mesh_file)
    elif mesh_file.suffix.lower() == ".gltf":
        companions = _gltf_companions(mesh_file)
    else:  # a single-file format, packed for a recorded gravity beside it
        companions = []
    companions += recorded_gravity_files(mesh_file.parent)  # levelling evidence: kept beside the mesh
    base = mesh_file.parent
    files = [mesh_file] + [c for c in dict.fromkeys(companions) if is_inside(c, real_folder(mesh_file))]
    return base, files


def pack_source(source: Path, mesh_file: Path, workdir: Path, *, remember: bool = False) -> Path:
    """The single file to upload for `source`: itself, or a deterministic zip of what the mesh needs.
    `remember`: keep the zip's bytes for the next pack_source of the same files in this process (which takes
    them), and read and keep it in the user's packed cache (packed_cache: a command's, not the service's)."""
    if _stored_as_is(source):
        return source
    base, files = _files_to_pack(source, mesh_file)
    total = sum(f.stat().st_size for f in files)
    if total > MAX_PACKED_BYTES:
        raise SpaceError(f"{source.name}: {total} bytes of mesh files exceed the limit {MAX_PACKED_BYTES}")
    out = workdir / f"{mesh_file.stem}.zip"
    key = (str(base), tuple((str(f), (st := f.stat()).st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
                                for f in files))
    # zipped earlier in this process (checksum, then register)
    if (packed := _PACKED.pop(key, None)) is not None:
        out.write_bytes(packed)
        return out
    # zipped by an earlier run of this user's
    if remember and (packed := packed_cache.read((PACKER, key))) is not None:
        out.write_bytes(packed)
        _remember_pack(key, packed)
        return out
    _write_zip(out, base, files)
    if remember:
        packed = out.read_bytes()
        if len(packed) <= _PACKED_MAX_BYTES:
            packed_cache.keep((PACKER, key), packed)
        _remember_pack(key, packed)
    return out


def _stored_as_is(source: Path) -> bool:
    """True when `source` is uploaded itself: one file that needs nothing beside it, or a zip."""
    if (
        source.is_file()
        and source.suffix.lower() in SINGLE_FILE_SUFFIXES
        and scannet_companions(source) is None
        and _dataset_pack(source) is None
        and not recorded_gravity_files(source.parent)
    ):
        from services.core.ingest.capture.attach import capture_files_beside
        from services.core.ingest.guard.archive import MESH_SUFFIXES

        return source.suffix.lower() == ".zip" or not capture_files_beside(source, MESH_SUFFIXES)
    return False


def _write_zip(out: Path, base: Path, files: list[Path], *, before_stored_members: bool = False) -> None:
    """The deterministic zip of `files` (named relative to `base`): fixed timestamps and settings, so the same
    files give the same checksum. `before_stored_members`: every member deflated at zlib's default level, as
    sources were packed until 2026-11 (legacy_source_checksum)."""
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for f in files:
            info = zipfile.ZipInfo(f.relative_to(base).as_posix(), date_time=(1980, 1, 1, 0, 0, 0))
            stored = f.suffix.lower() in STORED_SUFFIXES and not before_stored_members
            info.compress_type = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
            level = None if stored or before_stored_members else PACK_DEFLATE_LEVEL
            zf.writestr(info, f.read_bytes(), compresslevel=level)


# Zips source_checksum made in this process, by their files (path, size, mtime, ctime, inode), until the next
# pack_source of the same files takes them: `omnidata generate` zips a source for its checksum and again to
# store it (register_space); zipping costs ~0.02 CPU-s for ICL's 2.7 MB OBJ, ~0.19 for the 7-Scenes kitchen
# (16 MB zip). Bounded (a dataset root's scenes are all checksummed before any is stored): past it, the oldest
# go first. A larger zip is neither remembered here nor kept in the user's packed cache.
_PACKED: dict[tuple[str, tuple[tuple[str, int, int, int, int], ...]], bytes] = {}
_PACKED_MAX_BYTES = 128 << 20


def _remember_pack(key: tuple[str, tuple[tuple[str, int, int, int, int], ...]], data: bytes) -> None:
    if len(data) > _PACKED_MAX_BYTES:
        return
    _PACKED[key] = data
    while sum(len(v) for v in _PACKED.values()) > _PACKED_MAX_BYTES:
        del _PACKED[next(iter(_PACKED))]


def validate_source(source_path: str | Path, **frame: Unpack[SpaceFrame]) -> LoadedSpace:
    """Load and validate a space without storing it (SpaceError says what is wrong); `frame`: load_space's."""
    return load_space(source_path, **frame)


def _frame_name(
    up_axis: str, up: Sequence[float] | None, source_to_world: Sequence[Sequence[float]] | None
) -> str:
    """What the space row's up_axis column records: the axis name, or how the frame was given."""
    return "matrix" if source_to_world is not None else "vector" if up is not None else up_axis


def _space_row(owner: str, name: str, mesh_file: Path, checksum: str, loaded: LoadedSpace, *,
               unit_scale: float | str, frame_name: str) -> Space:
    """The Space row of a loaded source (no id or source key yet)."""
    return Space(
        owner=owner,
        name=name,
        source_key="",
        source_format=mesh_file.suffix.lower().lstrip("."),
        checksum=checksum,
        unit_scale=loaded.units.scale if loaded.units is not None else float(unit_scale),
        up_axis=frame_name,
        source_to_world=loaded.source_to_world.tolist(),
        bounds=loaded.bounds.tolist(),
        face_count=int(loaded.face_count),
        vertex_count=int(len(loaded.mesh.vertices)),
        has_texture=bool(loaded.has_texture or loaded.has_vertex_colors),
        has_semantics=bool(loaded.has_semantics),
        validation={
            "mesh_file": mesh_file.name,
            "up_method": loaded.up_method,
            **loaded.frame_record(),
            "warnings": list(loaded.warnings),
            "has_uv_texture": bool(loaded.has_texture),
            "has_vertex_colors": bool(loaded.has_vertex_colors),
        },
    )


def register_space(
    session: Session,
    store: ObjectStore,
    *,
    owner: str,
    name: str,
    source_path: str | Path,
    key_prefix: str = "spaces",
    up_axis: str = "auto",
    unit_scale: float | str = "auto",
    up: Sequence[float] | None = None,
    source_to_world: Sequence[Sequence[float]] | None = None,
    loaded: LoadedSpace | None = None,
    accept_up_guess: bool = True,
) -> Space:
    """Validate a space, upload its source and add its row (flushed, not committed).

    `loaded`: the result of `validate_source` for the same path and options, so a caller that validated
    first does not load the mesh twice. An ambiguous up does not refuse the space: it is recorded (with
    both candidates) and the space needs a frame before a job may plan it (`services.core.db.frame_choice`);
    `accept_up_guess` is accepted for the frame keywords of a JobSpec and does not change that.
    """
    try:
        check_name("space name", name)
    except ValueError as e:
        raise SpaceError(str(e)) from None
    source = Path(source_path)
    if session.query(Space.id).filter_by(owner=owner, name=name).first() is not None:
        raise SpaceError(f"a space named {name!r} already exists")
    with owned_temp_dir("register") as tmp:
        work = Path(tmp)
        mesh_file = (
            resolve_source(source, work / "x") if source.suffix.lower() == ".zip" else resolve_source(source)
        )
        if loaded is None:
            loaded = load_space(
                source, up_axis=up_axis, unit_scale=unit_scale, up=up, source_to_world=source_to_world,
                accept_up_guess=True,
            )
        packed = pack_source(source, mesh_file, work)
        if packed.suffix.lower() == ".zip" and (problem := archive_refusal(packed)):
            raise SpaceError(f"{source.name}: packed for storage, {problem}")  # planning would refuse it
        checksum = sha256_file(packed)
        space = _space_row(owner, name, mesh_file, checksum, loaded,
                           unit_scale=unit_scale, frame_name=_frame_name(up_axis, up, source_to_world))
        session.add(space)
        session.flush()  # assigns the id used in the key
        space.source_key = f"{key_prefix.strip('/')}/{space.id}/{packed.name}"
        store.put_file(space.source_key, packed)
        session.flush()
    return space


def fetch_space(store: ObjectStore, space: Space, cache_dir: str | Path) -> Path:
    """Local path of a space's mesh file (or of the folder a zipped source unpacked to), downloaded (and
    unzipped) once per checksum into `cache_dir`."""
    cache = Path(cache_dir) / space.checksum
    done_marker = cache / ".ready"
    if not done_marker.exists():
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{space.checksum[:12]}-", dir=cache.parent))
        try:
            fname = Path(space.source_key).name
            store.get_file(space.source_key, tmp / fname)
            if fname.lower().endswith(".zip"):
                resolve_source(tmp / fname, tmp / "src")
                (tmp / fname).unlink()
            (tmp / ".ready").write_text(space.checksum)
            try:
                os.rename(tmp, cache)  # atomic: concurrent fetchers keep whichever lands first
            except OSError:
                if not done_marker.exists():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    # a zipped source comes back as its folder, so what was packed beside the mesh (a capture) is found with
    # it
    return cache / "src" if (cache / "src").is_dir() else resolve_source(next(
        p for p in cache.iterdir() if p.is_file() and p.name != ".ready"
    ))


@dataclass
class Source:
    """One SPACE argument: its path, name, and the checksum its registered source will have."""

    path: Path
    name: str
    checksum: str
    has_semantics: bool | None = None  # known once validated (None: already registered, trusted)
    loaded: LoadedSpace | None = None  # the validated space, handed to register_space so the mesh loads once
    from_root: bool = False  # one scene of a dataset root: refused alone (the others go on) when unusable
    refused: str | None = None  # why this scene of a dataset root cannot be used


def source_checksum(path: Path) -> str:
    """sha256 of the object register_space stores for `path` (the file itself, or its deterministic zip)."""
    with tempfile.TemporaryDirectory(prefix="omnidata-source-") as tmp:
        work = Path(tmp)
        mesh = resolve_source(path, work / "x") if path.suffix.lower() == ".zip" else resolve_source(path)
        return sha256_file(pack_source(path, mesh, work, remember=True))


def legacy_source_checksum(path: Path) -> str | None:
    """The checksum `path` had when sources were zipped with every member deflated at zlib's default level
    (before 2026-11), so an output folder of that time still resumes; None when `path` is stored as it is (not
    zipped)."""
    if _stored_as_is(path):
        return None
    with tempfile.TemporaryDirectory(prefix="omnidata-source-") as tmp:
        base, files = _files_to_pack(path, resolve_source(path))
        out = Path(tmp) / "legacy.zip"
        _write_zip(out, base, files, before_stored_members=True)
        return sha256_file(out)
