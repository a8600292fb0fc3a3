"""Object store in a local folder (the embedded default): one file per key under `root`."""

from __future__ import annotations

import errno
import hashlib
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path

from services.core.storage.base import (
    PROBE_KEY,
    ObjectInfo,
    ObjectNotFoundError,
    StorageError,
    StorageUnavailable,
    check_key,
    check_prefix,
    io_pool,
    sha256_file,
)

# in-flight writes (group 1: the target's name), never listed
_TMP = re.compile(r"^\.(.+)\.tmp-[0-9a-f]{32}$")
_CHUNK = 1024 * 1024
_FULL = (errno.ENOSPC, errno.EDQUOT)
# The probe's bar for "has room": a few views' outputs at 512 px (~6 MB a view). A folder that takes the
# probe's two bytes but not a view would let waiting work start only to fail again.
PROBE_MIN_FREE_BYTES = 8 * 2**20


class LocalStore:
    """Keys map to files under `root`; writes go to a temp file in the same folder, then os.replace
    (atomic)."""

    def __init__(self, root: str | Path, *, fsync: bool = True):
        self.root = Path(root).expanduser().resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync  # flush data before the rename so a committed task's output survives a crash

    def __repr__(self) -> str:
        return f"LocalStore({str(self.root)!r})"

    def path(self, key: str) -> Path:
        """The file that holds `key` (validated; never outside root, never through a symbolic link).

        A link under the root (a tenant's staging folder pointing at /etc, or at another tenant's
        objects) is not an object: ObjectNotFoundError, so nothing is ever read or written through it.
        """
        path = self.root.joinpath(*check_key(key).split("/"))
        if os.path.realpath(path) != str(path):
            raise ObjectNotFoundError(key)
        return path

    def _tmp(self, target: Path) -> Path:
        return target.with_name(f".{target.name}.tmp-{uuid.uuid4().hex}")

    def _commit(self, tmp: Path, target: Path) -> None:
        if self.fsync:
            _flush(tmp, drop_cached=False)
        os.replace(tmp, target)

    def _write_failed(self, e: OSError) -> StorageError:
        """The error of a failed write: StorageUnavailable for a full folder (it passes once space is freed),
        else StorageError (permission, read-only file system)."""
        if e.errno in _FULL:
            return StorageUnavailable(f"storage full: no space left in the object folder {self.root} "
                                      f"({e.strerror or e})")
        return StorageError(f"cannot write to the object folder {self.root}: {e.strerror or e}")

    @contextmanager
    def _writing(self, target: Path) -> Iterator[Path]:
        """A temp file beside `target`, renamed onto it by the caller; failures to write name the folder."""
        tmp = self._tmp(target)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            yield tmp
        except OSError as e:  # permission, read-only or full file system
            raise self._write_failed(e) from e
        finally:
            with suppress(OSError):  # the folder may not exist (the failure above): nothing to remove
                tmp.unlink(missing_ok=True)

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectInfo:
        target = self.path(key)
        with self._writing(target) as tmp:
            tmp.write_bytes(data)
            self._commit(tmp, target)
        return ObjectInfo(key, len(data), hashlib.sha256(data).hexdigest())

    def put_unflushed(self, key: str, buffers: Sequence[bytes | memoryview]) -> ObjectInfo:
        """Write `buffers` one after the other as `key` (no joined copy first), renamed into place but not
        flushed to disk and with no sha256: for a cache that a machine crash may tear and its reader
        rebuilds (`generate`'s pass sets: services.worker.run.pass_handoff)."""
        target = self.path(key)
        size = 0
        with self._writing(target) as tmp:
            with open(tmp, "wb") as f:
                for b in buffers:
                    size += f.write(b)
            os.replace(tmp, target)
        return ObjectInfo(key, size, None)

    def put_many(self, items: Sequence[tuple[str, bytes]], *, keep_cached: bool = True) -> list[ObjectInfo]:
        """Every temp file written, then flushed concurrently (the file system commits the flushes together:
        one journal commit instead of one per file, ~30-100 ms of waiting a view on this disk), then renamed.
        The checksums are computed while the flushes wait for the disk (~4 ms of a view's ~6 MB off its wall
        time). keep_cached=False: each file's pages leave the page cache once flushed (_flush)."""
        targets = [self.path(key) for key, _ in items]
        tmps: list[Path] = []
        try:
            for target, (_, data) in zip(targets, items, strict=True):
                target.parent.mkdir(parents=True, exist_ok=True)
                tmps.append(self._tmp(target))
                tmps[-1].write_bytes(data)
            # map submits every flush at once; its results are waited for below
            flushed = io_pool().map(lambda tmp: _flush(tmp, drop_cached=not keep_cached),
                                    tmps if self.fsync else [])
            infos = [ObjectInfo(key, len(data), hashlib.sha256(data).hexdigest()) for key, data in items]
            list(flushed)
            for tmp, target in zip(tmps, targets, strict=True):
                os.replace(tmp, target)
        except OSError as e:  # permission, read-only or full file system
            raise self._write_failed(e) from e
        finally:
            for tmp in tmps:
                with suppress(OSError):
                    tmp.unlink(missing_ok=True)
        return infos

    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectInfo:
        target = self.path(key)
        h = hashlib.sha256()
        size = 0
        with open(path, "rb") as src, self._writing(target) as tmp:
            with tmp.open("wb") as dst:
                while block := src.read(_CHUNK):
                    h.update(block)
                    dst.write(block)
                    size += len(block)
            self._commit(tmp, target)
        return ObjectInfo(key, size, h.hexdigest())

    def probe(self) -> None:
        """The root folder exists (it is not re-created here: a vanished mount must show), takes writes and
        has PROBE_MIN_FREE_BYTES free (StorageUnavailable "storage full" below that)."""
        if not self.root.is_dir():
            raise StorageError(f"the object folder {self.root} does not exist")
        self.put_bytes(PROBE_KEY, b"ok")
        self.delete(PROBE_KEY)
        free = shutil.disk_usage(self.root).free
        if free < PROBE_MIN_FREE_BYTES:
            raise StorageUnavailable(f"storage full: {free / 2**20:.1f} MiB left in the object folder "
                                     f"{self.root} (work waits for {PROBE_MIN_FREE_BYTES // 2**20} MiB)")

    def get_bytes(self, key: str) -> bytes:
        try:
            return self.path(key).read_bytes()
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise ObjectNotFoundError(key) from None

    def get_file(self, key: str, path: str | Path) -> Path:
        src = self.path(key)
        if not src.is_file():
            raise ObjectNotFoundError(key)
        dest = Path(path)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._tmp(dest)
        try:
            shutil.copyfile(src, tmp)
            os.replace(tmp, dest)
        finally:
            tmp.unlink(missing_ok=True)
        return dest

    def exists(self, key: str) -> bool:
        try:
            return self.path(key).is_file()
        except ObjectNotFoundError:
            return False

    def stat(self, key: str) -> ObjectInfo | None:
        """Size and sha256 (computed from the file: O(size))."""
        try:
            p = self.path(key)
        except ObjectNotFoundError:
            return None
        if not p.is_file():
            return None
        return ObjectInfo(key, p.stat().st_size, sha256_file(p))

    def delete(self, key: str) -> bool:
        try:
            p = self.path(key)
            p.unlink()
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            return False
        self._prune(p.parent)
        return True

    def _prune(self, folder: Path) -> None:
        # Remove folders left empty by deletes, up to the root; a concurrent writer may refill one: ignore.
        while folder != self.root and self.root in folder.parents:
            try:
                folder.rmdir()
            except OSError:
                return
            folder = folder.parent

    def delete_prefix(self, prefix: str) -> int:
        """Delete the objects under `prefix`, and the temp files of writes to keys under it (a writer killed
        mid-write left them; one still writing fails its rename, which is what deleting its key asks)."""
        n = 0
        for key in list(self.list(prefix)):
            n += self.delete(key)
        for tmp in self._temp_files(self._walk_base(prefix)):
            rel = tmp.parent.relative_to(self.root).as_posix()
            match = _TMP.match(tmp.name)
            target = match.group(1) if match else ""
            if (target if rel == "." else f"{rel}/{target}").startswith(prefix):
                tmp.unlink(missing_ok=True)
                self._prune(tmp.parent)
        return n

    def _walk_base(self, prefix: str) -> Path:
        # The deepest folder a listing prefix names: keys under it are all in there.
        folder_part = prefix.rsplit("/", 1)[0] if "/" in prefix else ""
        return self.root.joinpath(*folder_part.split("/")) if folder_part else self.root

    def _temp_files(self, base: Path) -> Iterator[Path]:
        for dirpath, _dirs, files in os.walk(base):
            for name in files:
                if _TMP.match(name):
                    yield Path(dirpath) / name

    def list(self, prefix: str = "") -> Iterator[str]:
        check_prefix(prefix)
        # Walk only the deepest folder the prefix names, then filter by the string prefix (S3 semantics).
        base = self._walk_base(prefix)
        if not base.is_dir():
            return iter(())
        keys = []
        for dirpath, _dirs, files in os.walk(base):
            rel = Path(dirpath).relative_to(self.root).as_posix()
            for name in files:
                if _TMP.match(name):
                    continue
                key = name if rel == "." else f"{rel}/{name}"
                if key.startswith(prefix):
                    keys.append(key)
        return iter(sorted(keys))

    def remove_temp_files(self, older_than_s: float | None = None) -> int:
        """Delete the temp files of writes that never committed (a writer killed mid-write); returns how many.

        Without `older_than_s`: every one, for when no writer runs on this folder (before an interrupted job
        is resumed). With it: those not written to for that long, safe beside running writers (a write in
        flight touches its file every chunk and renames it within seconds).
        """
        cutoff = None if older_than_s is None else time.time() - older_than_s
        removed = 0
        for tmp in self._temp_files(self.root):
            try:
                if cutoff is not None and tmp.stat().st_mtime > cutoff:
                    continue
                tmp.unlink()
            except FileNotFoundError:  # its writer committed or cleaned it meanwhile
                continue
            removed += 1
        return removed

    def presigned_url(self, key: str, expires_s: int = 3600) -> str:
        """file:// URI of the object (local files need no signature; `expires_s` is ignored)."""
        return self.path(key).as_uri()


def _flush(path: Path, *, drop_cached: bool) -> None:
    """fsync the file; with drop_cached, then drop its pages (clean once flushed) from the page cache. A
    worker writes a view's ~6 MB of outputs and never reads them again: kept, they only grow the cache and
    push out what is read again (the scan, the code), and every view's writes take pages afresh
    (bench/output/store_put.py; a 66-view ICL job: 0.5-0.7 s less, `generate` alternated with and without
    it)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        if drop_cached and hasattr(os, "posix_fadvise"):  # Linux and most Unixes; elsewhere they stay cached
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)
