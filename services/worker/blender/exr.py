"""Read the pass render's EXR without copying: Blender writes it single-part, scanline, uncompressed, float32.

Such a file is a header, a table of one offset per scanline, then per scanline: its y (int32), its byte count
(int32) and each channel's W samples in the header's channel order. One structured numpy dtype describes a
scanline, so every channel is a strided view of the file's bytes (no per-channel conversion: the OpenEXR
module's read costs ~4 ms per 512x512 view on one core). Anything else (compression, tiles, parts, half or
uint channels, subsampling) returns None and the caller reads it with the OpenEXR module.
tests/worker/blender/test_exr.py and test_pass_identity.py check the arrays against OpenEXR's.
"""

from __future__ import annotations

import mmap
import struct

import numpy as np

_MAGIC = 20000630
_SINGLE_PART_SCANLINE_MASK = 0x200 | 0x800 | 0x1000  # tiled, deep ("non-image"), multi-part: none of them
_FLOAT = 2  # pixel type FLOAT (32-bit)


def _header(buf: mmap.mmap) -> tuple[dict[str, bytes], int] | None:
    """Attribute name -> raw value, and the offset just after the header."""
    magic, version = struct.unpack_from("<ii", buf, 0)
    if magic != _MAGIC or version & _SINGLE_PART_SCANLINE_MASK:
        return None
    pos, attrs = 8, {}
    while buf[pos] != 0:
        name_end = buf.find(b"\0", pos)
        type_end = buf.find(b"\0", name_end + 1)
        (size,) = struct.unpack_from("<i", buf, type_end + 1)
        start = type_end + 5
        attrs[buf[pos:name_end].decode()] = buf[start:start + size]
        pos = start + size
    return attrs, pos + 1


def _channels(raw: bytes) -> list[str] | None:
    """Channel names of a chlist, in file order; None unless every channel is float32 and not subsampled."""
    names, pos = [], 0
    while raw[pos] != 0:
        end = raw.index(b"\0", pos)
        ptype, _linear, xs, ys = struct.unpack_from("<iB3xii", raw, end + 1)
        if ptype != _FLOAT or xs != 1 or ys != 1:
            return None
        names.append(raw[pos:end].decode())
        pos = end + 17
    return names


def read_channels(path: str) -> dict[str, np.ndarray] | None:
    """Channel name -> float32 H x W view of the file's bytes (Combined's R, G, B, A as
    `<layer>.Combined.R`...), or None when the file is not a single-part uncompressed float32 scanline EXR.
    The views map the file (read only, no copy): decode them before the next render rewrites it."""
    with open(path, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    head = _header(buf)
    if head is None:
        return None
    attrs, pos = head
    names = _channels(attrs.get("channels", b"\0"))
    if names is None or attrs.get("compression") != b"\0" or attrs.get("lineOrder") != b"\0":
        return None
    x0, y0, x1, y1 = struct.unpack("<iiii", attrs["dataWindow"])
    w, h = x1 - x0 + 1, y1 - y0 + 1
    start = pos + 8 * h  # one offset per scanline (uncompressed: one scanline per block)
    line = np.dtype([("y", "<i4"), ("size", "<i4"), *((n, "<f4", (w,)) for n in names)])
    if len(buf) < start + h * line.itemsize:
        return None
    rows = np.frombuffer(buf, dtype=line, count=h, offset=start)
    if rows["size"][0] != 4 * w * len(names) or rows["y"][0] != y0 or rows["y"][-1] != y1:
        return None
    return {n: rows[n] for n in names}
