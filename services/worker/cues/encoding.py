"""File encodings of the cue catalog, the output contract readers decode: PNG 8/16-bit, .npy, float32 EXR,
JSON.

The catalog entry (ext, dtype, channels) decides the encoding; a value of the wrong dtype or shape is an
error, never silently converted, so a cue can not drift from its documented encoding.
"""

from __future__ import annotations

import io
import os
import struct
import tempfile
import zlib
from collections.abc import Callable

import numpy as np
from isal import isal_zlib

from services.core.domain.cues import get_cue
from services.core.domain.exr import decode_exr_rgb  # noqa: F401  (re-exported: the inverse of encode_exr_rgb)
from services.core.domain.plan_cues import encode_json
from services.core.temp_dirs import owned_prefix
from services.worker.cues.registry import CueValue

# PNGs are written here, not by Pillow: every row "Up"-filtered (the difference to the row above, vectorised)
# and deflated by ISA-L (isal_zlib, level 1). On a room view's 13 PNG cues at 512 px
# (bench/output/encode_cost.py, one core)
# that is ~7 ms against ~30 ms for zlib level 1 + Z_RLE (the encoder before) and ~135 ms for Pillow at level 3
# + Z_RLE, files ~5% smaller than zlib's; the Up filter gives the smallest files of None / Sub / Up with
# ISA-L, which is as fast on all three. Any deflater's stream decodes to the same array. ISA-L is a hard
# dependency (wheels for every platform the worker runs on): one deflater everywhere, so a view's files are
# the same bytes on every x86-64 worker (ISA-L's output is the same above SSE4.2) rather than whatever zlib
# build a Python links.
PNG_DEFLATE_LEVEL = 1  # ISA-L levels 0-3: 0 is no faster and ~15% larger, 2 the same, 3 three times slower
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_FILTER_UP = 2
_PNG_IEND = struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))


def deflate_png(data: memoryview) -> bytes:
    """The zlib stream of a PNG's filtered scanlines (ISA-L, PNG_DEFLATE_LEVEL)."""
    return isal_zlib.compress(data, PNG_DEFLATE_LEVEL)


def zlib_deflater(level: int, strategy: int = zlib.Z_DEFAULT_STRATEGY) -> Callable[[memoryview], bytes]:
    """A deflate for encode_png with Python's zlib at `level` (0-9) and `strategy` (0 default, 1 filtered, 2
    Huffman only, 3 RLE): the encoder before ISA-L was zlib_deflater(1, zlib.Z_RLE) (benchmarks and tests
    compare)."""

    def deflate(data: memoryview) -> bytes:
        compressor = zlib.compressobj(level, zlib.DEFLATED, 15, 9, strategy)
        return compressor.compress(data) + compressor.flush()

    return deflate


# The position EXR is stored uncompressed. bench/output/encodings.py on 12 room views at 512 px
# (bench/results/
# derivations.json "encodings"), write CPU ms / MB: none 1.8 / 3.15, RLE 5.3 / 3.15, ZIPS 21 / 2.22, ZIP
# (before) 23 / 1.93, PIZ 73 / 1.82, ZSTD 16 / 1.03, HTJ2K 13 / 0.97; all decode bit for bit. World XYZ floats
# hardly compress, so ZIP spent 17% of a bare render's CPU (0.12 s) to save 1.2 MB; ZSTD and HTJ2K need
# OpenEXR >= 3.5 / 3.4 (2025) to read, where an uncompressed file opens in every EXR reader. Uncompressed
# files are written here (the bytes OpenEXR's own writer gives, without its temp file); ZIP (a job's
# position_compression) goes through OpenEXR, imported then only (its module costs a worker ~0.09 CPU-s to
# load).
EXR_CODECS = ("none", "zip")  # CueParams.position_compression


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
        return encode_exr_rgb(arr, exr_compression)
    raise ValueError(f"cue {cue!r}: no encoder for .{spec.ext}")


def encode_png(arr: np.ndarray, deflate: Callable[[memoryview], bytes] = deflate_png) -> bytes:
    """PNG of a uint8 (H x W grey, H x W x 3 RGB) or uint16 (H x W grey, a true 16-bit PNG) array.

    deflate: the zlib stream of the filtered scanlines (ISA-L by default; zlib_deflater for zlib's)."""
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
    idat = deflate(filtered.data)
    header = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    # The IDAT's CRC runs over its type and body without joining them (the body is the file's bulk).
    return b"".join((_PNG_SIGNATURE, _png_chunk(b"IHDR", header), struct.pack(">I", len(idat)), b"IDAT", idat,
                     struct.pack(">I", isal_zlib.crc32(idat, isal_zlib.crc32(b"IDAT"))), _PNG_IEND))


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def encode_npy(arr: np.ndarray) -> bytes:
    """A standard .npy file (np.load reads it back)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def encode_exr_rgb(arr: np.ndarray, compression: str = "none") -> bytes:
    """A scanline float32 EXR with R, G, B channels of an H x W x 3 float32 array; `compression` one of
    EXR_CODECS."""
    arr = np.asarray(arr)
    if arr.dtype != np.float32 or arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"an RGB EXR needs an H x W x 3 float32 array, got {arr.dtype} {arr.shape}")
    if compression not in EXR_CODECS:
        raise ValueError(f"EXR compression {compression!r} is not one of {', '.join(EXR_CODECS)}")
    if compression == "none":
        return _exr_uncompressed_rgb(arr)
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    shm = "/dev/shm" if os.access("/dev/shm", os.W_OK) else None
    fd, path = tempfile.mkstemp(prefix=owned_prefix("exr"), suffix=".exr", dir=shm)
    os.close(fd)
    try:
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(arr)}) as f:
            f.write(path)
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.remove(path)


def _exr_attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def _exr_uncompressed_rgb(arr: np.ndarray) -> bytes:
    """The single-part scanline EXR OpenEXR writes for {"RGB": arr} with NO_COMPRESSION, byte for byte (the
    tests compare with OpenEXR's file): magic and version 2, the header's attributes in name order, then the
    offset table (uint64 per line) and one block per line: y, byte count, then the B, G, R rows (channels in
    name order), all little-endian."""
    h, w = arr.shape[:2]
    channel = struct.pack("<iB3xii", 2, 0, 1, 1)  # FLOAT, not linear, x and y sampling 1
    window = struct.pack("<4i", 0, 0, w - 1, h - 1)
    head = b"".join(
        (
            b"\x76\x2f\x31\x01", struct.pack("<I", 2),
            _exr_attribute(
                "channels", "chlist", b"".join(c + b"\0" + channel for c in (b"B", b"G", b"R")) + b"\0"
            ),
            _exr_attribute("compression", "compression", b"\0"),
            _exr_attribute("dataWindow", "box2i", window), _exr_attribute("displayWindow", "box2i", window),
            _exr_attribute("lineOrder", "lineOrder", b"\0"),  # increasing y
            _exr_attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
            _exr_attribute("screenWindowCenter", "v2f", struct.pack("<2f", 0.0, 0.0)),
            _exr_attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)),
            _exr_attribute("type", "string", b"scanlineimage"), b"\0",
        )
    )
    line = 8 + 12 * w
    start = len(head) + 8 * h
    out = np.empty(start + h * line, dtype=np.uint8)
    out[:len(head)] = np.frombuffer(head, dtype=np.uint8)
    out[len(head):start].view("<u8")[:] = start + line * np.arange(h, dtype=np.uint64)
    blocks = out[start:].reshape(h, line)
    counts = blocks[:, :8].view("<i4")
    counts[:, 0] = np.arange(h)
    counts[:, 1] = 12 * w
    blocks[:, 8:].view("<f4").reshape(h, 3, w)[:] = arr[:, :, ::-1].transpose(0, 2, 1)
    return out.tobytes()
