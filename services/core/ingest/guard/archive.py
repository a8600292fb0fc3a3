"""Finding the one mesh of a space: a file, the only mesh in a folder, or in a zip extracted safely.

A zip is untrusted input: traversal, absolute paths, links, encryption and zip bombs are refused before
and while extracting (the sizes in its headers can lie, so the bytes written are counted).
"""

from __future__ import annotations

import stat
import tempfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import TypedDict, Unpack

from services.core.ingest.datasets import scene_mesh_in
from services.core.ingest.errors import SpaceError
from services.core.ingest.formats import SCANNET_MESH_SUFFIX
from services.core.ingest.guard.archive_rules import MAX_RATIO, expansion_refusal
from services.core.ingest.pointcloud import CLOUD_SUFFIXES
from services.core.temp_dirs import owned_prefix

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", *CLOUD_SUFFIXES)


ZIP_MAX_TOTAL_BYTES = 8 * 1024**3  # uncompressed size of all members


ZIP_MAX_RATIO = MAX_RATIO  # uncompressed / compressed, per member and in total: one rule (archive_rules)


ZIP_MAX_MEMBERS = 20_000


def _is_hidden(p: Path) -> bool:
    return any(part.startswith(".") or part == "__MACOSX" for part in p.parts)


def _meshes_in(folder: Path) -> list[Path]:
    found = [
        p for p in sorted(folder.rglob("*"))
        if p.is_file() and p.suffix.lower() in MESH_SUFFIXES and not _is_hidden(p.relative_to(folder))
    ]
    return found


def safe_extract_zip(
    zip_path: Path,
    dest: Path,
    *,
    max_total_bytes: int = ZIP_MAX_TOTAL_BYTES,
    max_ratio: float = ZIP_MAX_RATIO,
    max_members: int = ZIP_MAX_MEMBERS,
) -> None:
    """Extract `zip_path` into `dest`, refusing traversal, absolute paths, links and zip bombs
    (SpaceError)."""
    name = zip_path.name
    try:
        zf = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise SpaceError(f"{name}: not a readable zip archive ({e})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise SpaceError(
                f"{name}: {len(infos)} members in the archive, more than the limit {max_members}"
            )
        _check_headers(name, infos, max_total_bytes, max_ratio)
        dest = dest.resolve()
        dest.mkdir(parents=True, exist_ok=True)
        written = 0
        for info in infos:
            member = info.filename.replace("\\", "/")
            target = (dest / member).resolve()
            if dest != target and dest not in target.parents:
                raise SpaceError(f"{name}: member {info.filename!r} escapes the extraction folder")
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            written = _extract_member(zf, info, target, name, written, max_total_bytes)


def _check_member(name: str, info: zipfile.ZipInfo) -> None:
    """Refuse a member with an absolute path, a '..', a symbolic link or encryption."""
    raw = info.filename
    member = raw.replace("\\", "/")
    pure = PurePosixPath(member)
    if member.startswith("/") or (len(member) > 1 and member[1] == ":"):
        raise SpaceError(f"{name}: member {raw!r} has an absolute path; refusing to extract")
    if ".." in pure.parts:
        raise SpaceError(f"{name}: member {raw!r} climbs out of the archive ('..'); refusing to extract")
    if not pure.parts or pure.parts == (".",):
        raise SpaceError(f"{name}: member {raw!r} names no file (it is the archive's own folder); "
                         "refusing to extract")
    mode = info.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise SpaceError(f"{name}: member {raw!r} is a symbolic link; refusing to extract")
    if info.flag_bits & 0x1:
        raise SpaceError(f"{name}: member {raw!r} is encrypted")


def _check_headers(name: str, infos: list[zipfile.ZipInfo], max_total_bytes: int, max_ratio: float) -> None:
    """Every member's name, and the sizes the headers declare (per member and in total), before extracting."""
    total = 0
    total_compressed = 0
    for info in infos:
        _check_member(name, info)
        total += info.file_size
        total_compressed += info.compress_size
        if problem := expansion_refusal(
            f"member {info.filename!r}", info.file_size, info.compress_size, max_ratio
        ):
            raise SpaceError(f"{name}: {problem}")
    if total > max_total_bytes:
        raise SpaceError(
            f"{name}: uncompressed size {total} bytes exceeds the limit {max_total_bytes}: "
            "refusing a possible zip bomb"
        )
    if problem := expansion_refusal("archive", total, total_compressed, max_ratio):
        raise SpaceError(f"{name}: {problem}")


def _extract_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, name: str, written: int,
                    max_total_bytes: int) -> int:
    """Stream one member to `target` with our own count (the sizes in the headers can lie); returns the bytes
    written by the extraction so far, this member included."""
    try:
        with zf.open(info) as src, open(target, "wb") as out:
            member_bytes = 0
            while chunk := src.read(1 << 20):
                member_bytes += len(chunk)
                written += len(chunk)
                if member_bytes > info.file_size or written > max_total_bytes:
                    raise SpaceError(
                        f"{name}: member {info.filename!r} inflates past its declared size: "
                        "refusing a possible zip bomb"
                    )
                out.write(chunk)
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, ValueError) as e:
        # bad CRC, corrupt deflate stream, cut-off member, unknown compression method
        raise SpaceError(
            f"{name}: member {info.filename!r} is corrupt ({e}); re-create the archive"
        ) from None
    except OSError as e:  # a file member where a folder of the same name was extracted, and the like
        raise SpaceError(
            f"{name}: member {info.filename!r} cannot be extracted ({e.strerror or e})"
        ) from None
    return written


class ZipLimits(TypedDict, total=False):
    """Keyword arguments of safe_extract_zip that override its limits."""

    max_total_bytes: int
    max_ratio: float
    max_members: int


def resolve_source(
    path: str | Path,
    extract_dir: str | Path | None = None,
    **zip_limits: Unpack[ZipLimits],
) -> Path:
    """The one mesh file of a space: the file itself, the only mesh in a folder, or in a zip.

    A zip is extracted safely (see `safe_extract_zip`) into `extract_dir`, or into a new temporary
    folder that the caller owns when `extract_dir` is None.
    """
    p = Path(path)
    if not p.exists():
        raise SpaceError(f"{p}: no such file or folder")
    if p.is_file() and p.suffix.lower() == ".zip":
        dest = (
            Path(extract_dir)
            if extract_dir is not None
            else Path(tempfile.mkdtemp(prefix=owned_prefix("space")))
        )
        safe_extract_zip(p, dest, **zip_limits)
        return _one_mesh(dest, f"archive {p.name}")
    if p.is_file():
        if p.suffix.lower() not in MESH_SUFFIXES:
            raise SpaceError(
                f"{p.name}: unsupported file type {p.suffix or '(none)'!r}; "
                f"use one of {', '.join(MESH_SUFFIXES)} or a folder/.zip holding one"
            )
        return p
    if p.is_dir():
        return _one_mesh(p, f"folder {p}")
    raise SpaceError(f"{p}: not a file or folder")


def _one_mesh(folder: Path, what: str) -> Path:
    dataset_mesh = scene_mesh_in(folder)  # a public dataset's scene folder: the mesh its layout renders
    if dataset_mesh is not None:
        return dataset_mesh
    meshes = _meshes_in(folder)
    if not meshes:
        raise SpaceError(f"{what} holds no mesh ({', '.join(MESH_SUFFIXES)})")
    scannet = [m for m in meshes if m.name.endswith(SCANNET_MESH_SUFFIX)]
    if len(meshes) > 1 and len(scannet) == 1:  # a ScanNet scene folder: its other PLYs are derived copies
        return scannet[0]
    if len(meshes) > 1:
        listed = ", ".join(str(m.relative_to(folder)) for m in meshes[:20])
        more = f" and {len(meshes) - 20} more" if len(meshes) > 20 else ""
        raise SpaceError(f"{what} holds {len(meshes)} meshes, expected exactly one: {listed}{more}")
    return meshes[0]
