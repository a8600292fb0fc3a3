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
from typing import IO, TYPE_CHECKING

import anyio
from fastapi import HTTPException, Request, status
from python_multipart.multipart import MultipartParser, MultipartState, parse_options_header

if TYPE_CHECKING:  # defined for type checkers only
    from python_multipart.multipart import MultipartCallbacks

FILE_FIELD = "file"
# optional: a .zip of the scan's posed capture (photos + poses), sent beside the scan
CAPTURE_FIELD = "capture"
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
        """Do the queued work, in order (called in a worker thread; hashlib releases the GIL on big
        buffers)."""
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


class _FormReader:
    """The python-multipart callbacks of one request, sharing its parse state: the current part and its
    headers, the file work queued for a worker thread, and the first error (raised after the chunk)."""

    def __init__(self, dest_dir: Path, max_bytes: int) -> None:
        self.dest_dir = dest_dir
        self.max_bytes = max_bytes
        self.up = Upload()
        self.part = _Part()
        self.headers: dict[bytes, bytes] = {}
        self.files = _FileOps()
        self.errors: list[HTTPException] = []

    def callbacks(self) -> MultipartCallbacks:
        return {
            "on_part_begin": self.on_part_begin,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
        }

    def fail(self, code: int, msg: str) -> None:
        if not self.errors:
            self.errors.append(HTTPException(code, msg))

    def on_part_begin(self) -> None:
        self.headers.clear()
        self.part = _Part()

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self.part.hname += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self.part.hval += data[start:end]

    def on_header_end(self) -> None:
        self.headers[self.part.hname.lower()] = self.part.hval
        self.part.hname, self.part.hval = b"", b""

    def on_headers_finished(self) -> None:
        _disp, opts = parse_options_header(self.headers.get(b"content-disposition", b""))
        self.part.name = opts.get(b"name", b"").decode("utf-8", "replace")
        if b"filename" in opts and self.part.name == CAPTURE_FIELD:
            self._open_capture(opts[b"filename"].decode("utf-8", "replace"))
        elif b"filename" in opts:
            self._open_scan(opts[b"filename"].decode("utf-8", "replace"))
        elif len(self.up.fields) >= MAX_FIELDS:
            self.fail(status.HTTP_422_UNPROCESSABLE_CONTENT, f"too many form fields (at most {MAX_FIELDS})")

    def _open_capture(self, name: str) -> None:
        if self.up.capture_path is not None:
            self.fail(status.HTTP_422_UNPROCESSABLE_CONTENT, "send at most one 'capture' part")
            return
        if not name.lower().endswith(".zip"):
            self.fail(
                status.HTTP_422_UNPROCESSABLE_CONTENT, "the 'capture' part must be a .zip of the capture"
            )
            return
        (self.dest_dir / CAPTURE_FIELD).mkdir(exist_ok=True)
        self.up.capture_path = self.dest_dir / CAPTURE_FIELD / "capture.zip"
        self.files.open(self.up.capture_path)
        self.part.is_file = True

    def _open_scan(self, name: str) -> None:
        if self.part.name != FILE_FIELD:
            self.fail(
                status.HTTP_422_UNPROCESSABLE_CONTENT,
                f"unexpected file part {self.part.name!r}: send the scan as 'file' (and a "
                "capture .zip as 'capture')",
            )
            return
        if self.up.filename is not None:
            self.fail(status.HTTP_422_UNPROCESSABLE_CONTENT, "send exactly one 'file' part")
            return
        try:
            self.up.filename = safe_filename(name)
        except HTTPException as e:
            self.errors.append(e)
            return
        self.up.path = self.dest_dir / self.up.filename
        self.files.open(self.up.path)
        self.part.is_file = True

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.errors:
            return
        chunk = data[start:end]
        if self.part.is_file:
            self.up.size += len(chunk)
            if self.up.size > self.max_bytes:
                self.errors.append(_too_large(self.max_bytes))
                return
            self.files.write(chunk)
        elif len(self.part.buf) + len(chunk) > MAX_FIELD_BYTES:
            self.fail(status.HTTP_422_UNPROCESSABLE_CONTENT, f"form field {self.part.name!r} is too long")
        else:
            self.part.buf.extend(chunk)

    def on_part_end(self) -> None:
        part = self.part
        if part.is_file:  # the next file part opens its own file
            self.files.close()
        if self.errors or part.is_file or not part.name:
            return
        self.up.fields[part.name] = part.buf.decode("utf-8", "replace")

    def finished(self) -> Upload:
        """The upload, once the body has been read to its closing boundary."""
        up = self.up
        if up.path is None:
            raise HTTPException(
                status.HTTP_422_UNPROCESSABLE_CONTENT, "the form has no 'file' part with the scan"
            )
        if up.size == 0:
            raise HTTPException(
                status.HTTP_422_UNPROCESSABLE_CONTENT, f"uploaded file {up.filename!r} is empty"
            )
        up.sha256 = self.files.sha.hexdigest()
        return up


def _boundary(request: Request, max_bytes: int) -> bytes:
    """The multipart boundary; 415 for another content type, 413 when the declared length is already too
    large."""
    ctype, params = parse_options_header(request.headers.get("content-type", ""))
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            "send the space as multipart/form-data with a 'file' part (and optional name, "
            "up_axis, unit_scale)",
        )
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > max_bytes + MULTIPART_OVERHEAD:
        raise _too_large(max_bytes)
    return params[b"boundary"]


async def receive_upload(request: Request, *, dest_dir: Path, max_bytes: int) -> Upload:
    """Parse a multipart/form-data body, writing its `file` part to `dest_dir`; 413 past `max_bytes`."""
    boundary = _boundary(request, max_bytes)
    form = _FormReader(dest_dir, max_bytes)
    parser = MultipartParser(boundary, form.callbacks())
    try:
        async for chunk in request.stream():
            try:
                parser.write(chunk)
            except Exception as e:  # python-multipart raises its own errors on malformed bodies
                raise HTTPException(status.HTTP_400_BAD_REQUEST, f"malformed multipart body: {e}") from None
            if form.errors:
                raise form.errors[0]
            if form.files.queue:
                await anyio.to_thread.run_sync(form.files.run)
        if form.errors:
            raise form.errors[0]
        if parser.state != MultipartState.END:
            # python-multipart's finalize() does not check this: a body cut short would pass as a short file
            raise HTTPException(status.HTTP_400_BAD_REQUEST, "incomplete multipart body: no closing boundary")
    finally:
        form.files.abandon()
    return form.finished()
