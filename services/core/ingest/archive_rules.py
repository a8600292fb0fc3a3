"""One compression rule for every archive the service reads, and for every mesh it will pack into one.

The service stores an .obj (or a folder, a .gltf with buffers) as a zip of its files, and planning and
rendering extract that zip with the zip-bomb checks of `safe_extract_zip`. A mesh that deflates more than
MAX_RATIO times (2.4 MB of one repeated face line) was accepted at upload and then refused by every job:
so the same rule is checked on the mesh file itself before it is parsed (streamed, stopping as soon as the
output proves the file is under the limit: a real scan costs a few megabytes of deflate), on the zip the
service packs, and on every zip it extracts.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

MAX_RATIO = 200.0  # uncompressed / compressed, per member and in total
CHECKED_FROM_BYTES = 1_000_000  # smaller members cannot make a bomb worth refusing
_CHUNK = 1 << 20


def expansion_refusal(what: str, size: int, compressed: int, max_ratio: float = MAX_RATIO) -> str | None:
    """The message refusing `what` (`size` bytes stored in `compressed`), or None when it is within the rule."""
    if size > CHECKED_FROM_BYTES and size > max_ratio * max(compressed, 1):
        return (
            f"{what} expands {size / max(compressed, 1):.0f}x (limit {max_ratio:.0f}x): "
            "refusing a possible zip bomb (or a mesh of one repeated line)"
        )
    return None


def file_expansion_refusal(path: Path, max_ratio: float = MAX_RATIO) -> str | None:
    """The rule applied to a file as the packer will deflate it; None once the output shows it is under the limit."""
    size = path.stat().st_size
    if size <= CHECKED_FROM_BYTES:
        return None
    enough = size / max_ratio  # compressed bytes past which the file is within the rule
    deflate = zlib.compressobj(zlib.Z_DEFAULT_COMPRESSION, zlib.DEFLATED, -15)  # what zipfile's ZIP_DEFLATED does
    written = 0
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            written += len(deflate.compress(chunk))
            if written > enough:
                return None
    written += len(deflate.flush())
    return expansion_refusal("the mesh file", size, written, max_ratio)


def archive_refusal(zip_path: Path, max_ratio: float = MAX_RATIO) -> str | None:
    """The rule applied to the members (and the whole) of a zip, from its central directory."""
    with zipfile.ZipFile(zip_path) as zf:
        infos = zf.infolist()
    for info in infos:
        problem = expansion_refusal(f"member {info.filename!r}", info.file_size, info.compress_size, max_ratio)
        if problem is not None:
            return problem
    total = sum(i.file_size for i in infos)
    return expansion_refusal("archive", total, sum(i.compress_size for i in infos), max_ratio)
