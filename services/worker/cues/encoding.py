"""File encodings of the cue catalog, the output contract readers decode: PNG 8/16-bit, .npy, float32 EXR,
JSON.

The catalog entry (ext, dtype, channels) decides the encoding; a value of the wrong dtype or shape is an error,
never silently converted, so a cue can not drift from its documented encoding.
"""

from __future__ import annotations

import io
import os
import struct
import tempfile
import zlib

import numpy as np
import OpenEXR

from services.core.domain.cues import get_cue
from services.core.domain.exr import decode_exr_rgb  # noqa: F401  (re-exported: the inverse of encode_exr_rgb)
from services.core.domain.plan_cues import encode_json
from services.core.temp_dirs import owned_prefix
from services.worker.cues.registry import CueValue

# PNGs are written here, not by Pillow: every row "Up"-filtered (the difference to the row above, vectorised) and
# deflated by zlib with the Z_RLE strategy. On a room view's 12 PNG cues at 512 px (bench/derivations.py) that is
# ~55 ms against ~135 ms for Pillow at level 3 + Z_RLE (Pillow tries all five filters on every row), files ~10%
# larger. Z_RLE only looks for runs, so its level changes nothing; every setting decodes to the same array.
PNG_COMPRESS_LEVEL = 1
PNG_ZLIB_STRATEGY = zlib.Z_RLE
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_FILTER_UP = 2


# The position EXR is stored uncompressed. bench/encodings.py on 12 room views at 512 px (bench/results/
# derivations.json "encodings"), write CPU ms / MB: none 1.8 / 3.15, RLE 5.3 / 3.15, ZIPS 21 / 2.22, ZIP (before)
# 23 / 1.93, PIZ 73 / 1.82, ZSTD 16 / 1.03, HTJ2K 13 / 0.97; all decode bit for bit. World XYZ floats hardly
# compress, so ZIP spent 17% of a bare render's CPU (0.12 s) to save 1.2 MB; ZSTD and HTJ2K need OpenEXR >= 3.5 /
# 3.4 (2025) to read, where an uncompressed file opens in every EXR reader.
EXR_COMPRESSION = OpenEXR.NO_COMPRESSION
EXR_CODECS = {"none": OpenEXR.NO_COMPRESSION, "zip": OpenEXR.ZIP_COMPRESSION}  # CueParams.position_compression


def encode(cue: str, value: CueValue, *, exr_compression: str = "none") -> bytes:
    """Bytes of the file for `cue` holding `value` (array in the catalog dtype, dict for JSON, bytes for npz);
    `exr_compression` is a key of EXR_CODECS (the job's position_compression)."""
    spec = get_cue(cue)
    if spec.ext == "json":
        return encode_json(value)
    if spec.ext == "npz":
        if not isinstance(value, bytes | bytearray):
            raise TypeError(f"cue {cue!r} is stored as prepared .npz bytes, got {type(value).__name__}")
        return bytes(value)
    arr = np.asarray(value)
    if arr.dtype != np.dtype(spec.dtype):
        raise TypeError(f"cue {cue!r} must be {spec.dtype}, got {arr.dtype}")
    want_ndim = 2 if spec.channels == 1 else 3
    if arr.ndim != want_ndim or (spec.channels > 1 and arr.shape[2] != spec.channels):
        raise ValueError(f"cue {cue!r} must be H x W" + ("" if spec.channels == 1 else f" x {spec.channels}")
                         + f", got shape {arr.shape}")
    if spec.ext == "png":
        return encode_png(arr)
    if spec.ext == "npy":
        return encode_npy(arr)
    if spec.ext == "exr":
        return encode_exr_rgb(arr, EXR_CODECS[exr_compression])
    raise ValueError(f"cue {cue!r}: no encoder for .{spec.ext}")


def encode_png(arr: np.ndarray, level: int = PNG_COMPRESS_LEVEL, strategy: int = PNG_ZLIB_STRATEGY) -> bytes:
    """PNG of a uint8 (H x W grey, H x W x 3 RGB) or uint16 (H x W grey, a true 16-bit PNG) array.

    level, strategy: zlib compression level (0-9) and strategy (0 default, 1 filtered, 2 Huffman only, 3 RLE)."""
    arr = np.asarray(arr)
    if arr.dtype == np.uint16:
        if arr.ndim != 2:
            raise ValueError("16-bit PNGs are single-channel here")
        bit_depth, colour_type = 16, 0
    elif arr.dtype == np.uint8 and (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
        bit_depth, colour_type = 8, 0 if arr.ndim == 2 else 2
    elif arr.dtype == np.uint8:
        raise ValueError(f"8-bit PNGs are H x W or H x W x 3 here, got shape {arr.shape}")
    else:
        raise TypeError(f"PNG needs uint8 or uint16, got {arr.dtype}")
    h, w = arr.shape[:2]
    rows = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder(">")).view(np.uint8).reshape(h, -1)
    filtered = np.empty((h, rows.shape[1] + 1), dtype=np.uint8)
    filtered[:, 0] = _PNG_FILTER_UP
    filtered[:1, 1:] = rows[:1]  # the row above the first is zeros
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])  # bytes wrap modulo 256, as the filter defines
    deflate = zlib.compressobj(level, zlib.DEFLATED, 15, 9, strategy)
    idat = deflate.compress(filtered.data) + deflate.flush()
    header = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    return b"".join((_PNG_SIGNATURE, _png_chunk(b"IHDR", header), _png_chunk(b"IDAT", idat),
                     _png_chunk(b"IEND", b"")))


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def encode_npy(arr: np.ndarray) -> bytes:
    """A standard .npy file (np.load reads it back)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def encode_exr_rgb(arr: np.ndarray, compression: OpenEXR.Compression = EXR_COMPRESSION) -> bytes:
    """A scanline float32 EXR with R, G, B channels of an H x W x 3 float32 array."""
    header = {"compression": compression, "type": OpenEXR.scanlineimage}
    fd, path = tempfile.mkstemp(prefix=owned_prefix("exr"), suffix=".exr", dir="/dev/shm" if os.access("/dev/shm", os.W_OK) else None)
    os.close(fd)
    try:
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(arr, dtype=np.float32)}) as f:
            f.write(path)
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.remove(path)
