"""Streaming multipart upload: the file part goes straight to a temp file, refused (413) past a size limit.

Starlette's form parser spools any file to disk without a bound, so a client could fill the disk before
the route runs; this parser counts bytes as they arrive and stops at `max_bytes`. Only the parsing runs on the
event loop: the parser's callbacks queue the file work (open, write, hash, close: `_FileOps`), and each
received chunk's queue runs in a worker thread, so fifty uploads never hold the loop on a slow disk.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import anyio
from fastapi import HTTPException, Request, status
from python_multipart.multipart import MultipartParser, MultipartState, parse_options_header

FILE_FIELD = "file"
CAPTURE_FIELD = "capture"  # optional: a .zip of the scan's posed capture (photos + poses), sent beside the scan
MAX_FIELDS = 16
MAX_FIELD_BYTES = 4096
MULTIPART_OVERHEAD = 64 * 1024  # headers and boundaries a Content-Length may add on top of the file
_SAFE_CHARS = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass
class Upload:
    """A received upload: the form's text fields and the file saved under `path`."""

    fields: dict[str, str] = field(default_factory=dict)
    filename: str | None = None
    path: Path | None = None
    size: int = 0
    capture_path: Path | None = None  # the capture .zip part, when one was sent
    sha256: str = ""


@dataclass
class _Part:
    """Parser state of the part being read."""

    name: str = ""
    is_file: bool = False
    buf: bytearray = field(default_factory=bytearray)
    hname: bytes = b""
    hval: bytes = b""


class _FileOps:
    """File work the parser's callbacks ask for, run later off the event loop (`run`, in a worker thread)."""

    def __init__(self) -> None:
        self.sha = hashlib.sha256()
        self.queue: list[tuple[str, Path | bytes | None]] = []
        self._out: IO[bytes] | None = None

    def open(self, path: Path) -> None:
        self.queue.append(("open", path))

    def write(self, data: bytes) -> None:
        self.queue.append(("write", data))

    def close(self) -> None:
        self.queue.append(("close", None))

    def run(self) -> None:
        """Do the queued work, in order (called in a worker thread; hashlib releases the GIL on big buffers)."""
        queue, self.queue = self.queue, []
        for op, arg in queue:
            if op == "open":
                assert isinstance(arg, Path)
                self._out = arg.open("wb")
            elif op == "write" and self._out is not None:
                assert isinstance(arg, bytes)
                self.sha.update(arg)
                self._out.write(arg)
            elif op == "close" and self._out is not None:
                self._out.close()
                self._out = None

    def abandon(self) -> None:
        """Close an open file (the request failed); queued work is dropped."""
        self.queue.clear()
        if self._out is not None:
            self._out.close()
            self._out = None


def safe_filename(raw: str) -> str:
    """The client's file name reduced to a safe single path segment (no folders, no traversal)."""
    base = raw.replace("\\", "/").rsplit("/", 1)[-1]
    base = _SAFE_CHARS.sub("_", base).lstrip("._-")[:128]
    if not base or "." not in base:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"upload file name {raw!r} has no usable name or extension (e.g. scan.ply, room.zip)",
        )
    return base


def _too_large(max_bytes: int) -> HTTPException:
    return HTTPException(
        status.HTTP_413_CONTENT_TOO_LARGE,
        f"upload exceeds the limit of {max_bytes} bytes ({max_bytes / 2**20:.1f} MiB); "
        "register large scans from object storage instead (POST /spaces/register)",
    )


async def receive_upload(request: Request, *, dest_dir: Path, max_bytes: int) -> Upload:
    """Parse a multipart/form-data body, writing its `file` part to `dest_dir`; 413 past `max_bytes`."""
    ctype, params = parse_options_header(request.headers.get("content-type", ""))
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            "send the space as multipart/form-data with a 'file' part (and optional name, up_axis, unit_scale)",
        )
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > max_bytes + MULTIPART_OVERHEAD:
        raise _too_large(max_bytes)

    up = Upload()
    part = _Part()
    headers: dict[bytes, bytes] = {}
    files = _FileOps()
    errors: list[HTTPException] = []

    def fail(code: int, msg: str) -> None:
        if not errors:
            errors.append(HTTPException(code, msg))

    def on_part_begin() -> None:
        nonlocal part
        headers.clear()
        part = _Part()

    def on_header_field(data: bytes, start: int, end: int) -> None:
        part.hname += data[start:end]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        part.hval += data[start:end]

    def on_header_end() -> None:
        headers[part.hname.lower()] = part.hval
        part.hname, part.hval = b"", b""

    def on_headers_finished() -> None:
        _disp, opts = parse_options_header(headers.get(b"content-disposition", b""))
        part.name = opts.get(b"name", b"").decode("utf-8", "replace")
        if b"filename" in opts and part.name == CAPTURE_FIELD:
            if up.capture_path is not None:
                fail(status.HTTP_422_UNPROCESSABLE_CONTENT, "send at most one 'capture' part")
                return
            name = opts[b"filename"].decode("utf-8", "replace")
            if not name.lower().endswith(".zip"):
                fail(status.HTTP_422_UNPROCESSABLE_CONTENT, "the 'capture' part must be a .zip of the capture")
                return
            (dest_dir / CAPTURE_FIELD).mkdir(exist_ok=True)
            up.capture_path = dest_dir / CAPTURE_FIELD / "capture.zip"
            files.open(up.capture_path)
            part.is_file = True
        elif b"filename" in opts:
            if part.name != FILE_FIELD:
                fail(status.HTTP_422_UNPROCESSABLE_CONTENT,
                     f"unexpected file part {part.name!r}: send the scan as 'file' (and a capture .zip as 'capture')")
                return
            if up.filename is not None:
                fail(status.HTTP_422_UNPROCESSABLE_CONTENT, "send exactly one 'file' part")
                return
            try:
                up.filename = safe_filename(opts[b"filename"].decode("utf-8", "replace"))
            except HTTPException as e:
                errors.append(e)
                return
            up.path = dest_dir / up.filename
            files.open(up.path)
            part.is_file = True
        elif len(up.fields) >= MAX_FIELDS:
            fail(status.HTTP_422_UNPROCESSABLE_CONTENT, f"too many form fields (at most {MAX_FIELDS})")

    def on_part_data(data: bytes, start: int, end: int) -> None:
        if errors:
            return
        chunk = data[start:end]
        if part.is_file:
            up.size += len(chunk)
            if up.size > max_bytes:
                errors.append(_too_large(max_bytes))
                return
            files.write(chunk)
        elif len(part.buf) + len(chunk) > MAX_FIELD_BYTES:
            fail(status.HTTP_422_UNPROCESSABLE_CONTENT, f"form field {part.name!r} is too long")
        else:
            part.buf.extend(chunk)

    def on_part_end() -> None:
        if part.is_file:  # the next file part opens its own file
            files.close()
        if errors or part.is_file or not part.name:
            return
        up.fields[part.name] = part.buf.decode("utf-8", "replace")

    parser = MultipartParser(
        params[b"boundary"],
        {
            "on_part_begin": on_part_begin,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
        },
    )
    try:
        async for chunk in request.stream():
            try:
                parser.write(chunk)
            except Exception as e:  # python-multipart raises its own errors on malformed bodies
                raise HTTPException(status.HTTP_400_BAD_REQUEST, f"malformed multipart body: {e}") from None
            if errors:
                raise errors[0]
            if files.queue:
                await anyio.to_thread.run_sync(files.run)
        if errors:
            raise errors[0]
        if parser.state != MultipartState.END:
            # python-multipart's finalize() does not check this: a body cut short would pass as a short file
            raise HTTPException(status.HTTP_400_BAD_REQUEST, "incomplete multipart body: no closing boundary")
    finally:
        files.abandon()
    if up.path is None:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "the form has no 'file' part with the scan")
    if up.size == 0:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"uploaded file {up.filename!r} is empty")
    up.sha256 = files.sha.hexdigest()
    return up
