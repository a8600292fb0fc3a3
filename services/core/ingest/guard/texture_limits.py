"""Texture images are refused by the size their header declares, before anything decodes them.

A 5 KB PNG can declare 13000 x 13000 pixels (a worker then holds 2.3 GB to render it), and one past
Pillow's own bomb limit is dropped by trimesh without a word (the scan renders untextured). So every
texture a scan brings is measured from its header only and refused above MAX_TEXTURE_PIXELS, the same
rule at upload, planning and rendering: files a mesh names (served by the confined resolver), and the
images a GLB or glTF embeds (buffer views, data: URIs), read through a window on the file.
"""

from __future__ import annotations

import base64
import binascii
import io
import struct
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any, BinaryIO

from PIL import Image, UnidentifiedImageError

MAX_TEXTURE_SIDE = 8192
MAX_TEXTURE_PIXELS = MAX_TEXTURE_SIDE * MAX_TEXTURE_SIDE  # 67 Mpx: 256 MiB as RGBA, beyond any scan's atlas
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tga", ".tif", ".tiff", ".webp", ".gif", ".ppm", ".pgm"}
_MAGIC = (b"\x89PNG", b"\xff\xd8\xff", b"GIF8", b"BM", b"II*\x00", b"MM\x00*", b"RIFF")


def declared_size(stream: IO[bytes] | bytes) -> tuple[int, int] | None:
    """(width, height) an image's header declares, without decoding pixels; None when it is no image."""
    f = io.BytesIO(stream) if isinstance(stream, bytes) else stream
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            with Image.open(f) as img:  # reads the header only
                return int(img.size[0]), int(img.size[1])
        except Image.DecompressionBombError:  # Pillow's own limit is far above ours: over it for sure
            return (MAX_TEXTURE_SIDE * 64, MAX_TEXTURE_SIDE * 64)
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError, struct.error):
            return None


def size_refusal(what: str, size: tuple[int, int] | None) -> str | None:
    """The message refusing an image of `size` pixels, or None when it is within the limit."""
    if size is None or size[0] * size[1] <= MAX_TEXTURE_PIXELS:
        return None
    return (
        f"texture {what} declares {size[0]:,} x {size[1]:,} pixels, more than the limit of "
        f"{MAX_TEXTURE_PIXELS:,} ({MAX_TEXTURE_SIDE} x {MAX_TEXTURE_SIDE}); downscale it"
    )


def texture_refusal(name: str, data: bytes) -> str | None:
    """For a file a mesh names: the refusal when it is an image over the limit, else None."""
    if Path(name).suffix.lower() not in IMAGE_SUFFIXES and not data.startswith(_MAGIC):
        return None  # a material library or a buffer: not an image
    return size_refusal(repr(name), declared_size(data))


class _Window(io.RawIOBase):
    """A read-only view of `length` bytes of a file from `offset`: Pillow reads the header, nothing more."""

    def __init__(self, f: BinaryIO, offset: int, length: int):
        self._f, self._start, self._end, self._pos = f, offset, offset + length, offset

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:  # io's writable buffer protocol (typeshed: no len or slicing)
        n = max(0, min(len(b), self._end - self._pos))
        self._f.seek(self._pos)
        data = self._f.read(n)
        b[: len(data)] = data
        self._pos += len(data)
        return len(data)

    def seek(self, pos: int, whence: int = 0) -> int:
        base = {0: self._start, 1: self._pos, 2: self._end}[whence]
        self._pos = min(max(self._start, base + pos), self._end)
        return self._pos - self._start

    def tell(self) -> int:
        return self._pos - self._start


def embedded_refusal(source: Path, doc: Mapping[str, object], bin_offset: int | None) -> str | None:
    """For a glTF document (`bin_offset`: where a GLB's binary chunk starts): refusal of an embedded image."""
    images, views = doc.get("images"), doc.get("bufferViews")
    if not isinstance(images, list):
        return None
    with open(source, "rb") as f:
        for i, image in enumerate(images):
            if not isinstance(image, dict):
                continue
            size: tuple[int, int] | None = None
            uri, view = image.get("uri"), image.get("bufferView")
            if isinstance(uri, str) and uri.startswith("data:") and "base64," in uri:
                try:
                    size = declared_size(base64.b64decode(uri.split("base64,", 1)[1]))
                except (binascii.Error, ValueError):
                    size = None
            elif (
                isinstance(view, int)
                and bin_offset is not None
                and isinstance(views, list)
                and 0 <= view < len(views)
            ):
                bv = views[view] if isinstance(views[view], dict) else {}
                if bv.get("buffer", 0) == 0:
                    window = _Window(
                        f, bin_offset + int(bv.get("byteOffset", 0)), int(bv.get("byteLength", 0))
                    )
                    size = declared_size(io.BufferedReader(window))
            problem = size_refusal(f"image {i}", size)
            if problem is not None:
                return problem
    return None


def glb_bin_offset(source: Path) -> int | None:
    """Where the binary chunk's data of a GLB starts, or None when it has none."""
    with open(source, "rb") as f:
        head = f.read(20)
        if len(head) < 20:
            return None
        json_len = struct.unpack_from("<I", head, 12)[0]
        f.seek(20 + json_len)
        chunk = f.read(8)
        if len(chunk) < 8 or struct.unpack("<I", chunk[4:])[0] != 0x004E4942:
            return None
        return 20 + json_len + 8



_MATERIAL_IMAGES = (
    "image", "baseColorTexture", "normalTexture", "emissiveTexture", "metallicRoughnessTexture",
    "occlusionTexture",
)


def loaded_texture_refusal(loaded: object) -> str | None:
    """After trimesh has loaded a scan: the refusal for any material image over the limit (sizes from
    headers)."""
    geometries = loaded.geometry.values() if hasattr(loaded, "geometry") else [loaded]
    for geometry in geometries:
        material = getattr(getattr(geometry, "visual", None), "material", None)
        for attr in _MATERIAL_IMAGES:
            size = getattr(getattr(material, attr, None), "size", None)
            if isinstance(size, tuple) and len(size) == 2:
                problem = size_refusal(attr, (int(size[0]), int(size[1])))
                if problem is not None:
                    return problem
    return None
