"""One compression rule for every archive the service reads, and for every mesh it will pack into one.

The service stores an .obj (or a folder, a .gltf with buffers) as a zip of its files, and planning and
rendering extract that zip with the zip-bomb checks of `safe_extract_zip`. A mesh that deflates more than
MAX_RATIO times (2.4 MB of one repeated face line) was accepted at upload and then refused by every job:
so the same rule is checked on the mesh file itself before it is parsed (streamed, stopping as soon as the
output proves the file is under the limit: a real scan costs a piece or two of deflate), on the zip the
service packs, and on every zip it extracts.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

MAX_RATIO = 200.0  # uncompressed / compressed, per member and in total
CHECKED_FROM_BYTES = 1_000_000  # smaller members cannot make a bomb worth refusing
# Read and deflated in pieces this size: a real scan's first piece or two already deflate past the limit's
# bytes (ICL's 2.7 MB OBJ: 0.010 CPU-s; in 1 MB pieces, 0.093 s: no output before the first MB). Deflate's
# output does not depend on how its input is cut, so the verdict is the same for any piece size.
_CHUNK = 1 << 16


def expansion_refusal(what: str, size: int, compressed: int, max_ratio: float = MAX_RATIO) -> str | None:
    """The message refusing `what` (`size` bytes stored in `compressed`), or None when it is within the
    rule."""
    if size > CHECKED_FROM_BYTES and size > max_ratio * max(compressed, 1):
        return (
            f"{what} expands {size / max(compressed, 1):.0f}x (limit {max_ratio:.0f}x): "
            "refusing a possible zip bomb (or a mesh of one repeated line)"
        )
    return None


def file_expansion_refusal(path: Path, max_ratio: float = MAX_RATIO) -> str | None:
    """The rule applied to a file deflated at zlib's default level; None once the output shows it is under the
    limit.

    Stricter than the packed zip's check: the packer deflates at level 1 (services.core.ingest.registry),
    which compresses less, so a file this passes gives a packed zip its check passes too."""
    size = path.stat().st_size
    if size <= CHECKED_FROM_BYTES:
        return None
    enough = size / max_ratio  # compressed bytes past which the file is within the rule
    # what zipfile's ZIP_DEFLATED does
    deflate = zlib.compressobj(zlib.Z_DEFAULT_COMPRESSION, zlib.DEFLATED, -15)
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
        problem = expansion_refusal(
            f"member {info.filename!r}", info.file_size, info.compress_size, max_ratio
        )
        if problem is not None:
            return problem
    total = sum(i.file_size for i in infos)
    return expansion_refusal("archive", total, sum(i.compress_size for i in infos), max_ratio)
