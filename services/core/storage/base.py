"""Object storage contract: a small Protocol with a local-folder and an S3 backend, so every caller works on
a folder and on S3 alike.

Keys are '/'-separated relative paths ("rgb/omnidata/bunny/point_0_view_0_domain_rgb.png"). Absolute keys,
empty segments, '.', '..' and backslashes are refused with ValueError, so no key escapes a store's root.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """sha256 hex of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class ObjectInfo:
    """What a store knows about one object: size in bytes and sha256 hex when recorded."""

    key: str
    size: int
    sha256: str | None = None


class ObjectNotFoundError(FileNotFoundError):
    """The key names no object."""

    def __init__(self, key: str):
        self.key = key
        super().__init__(f"no object with key {key!r}")


class StorageError(OSError):
    """The object store itself failed (bucket missing, no write permission, endpoint down, disk full).

    The message names the store and the problem; the API answers it with 503 instead of a bare 500.
    """


class StorageUnavailable(StorageError):
    """The store cannot take work for now, for a reason outside the task: no space left (or over quota) in the
    object folder, an S3 endpoint answering 5xx, throttling or not answering. Work that meets it waits for the
    store (its attempt not counted) instead of failing; the message starts with what a person should read
    first ("storage full: ..." or "storage unavailable: ...")."""


def storage_outage(exc: BaseException | None) -> StorageUnavailable | None:
    """The StorageUnavailable `exc` is or was raised from (its causes and contexts), else None."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, StorageUnavailable):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


PROBE_KEY = "_ready/probe"  # written and deleted by `probe()`


def check_key(key: str) -> str:
    """Return `key` if it is a safe relative object key, else raise ValueError saying why."""
    if not isinstance(key, str) or not key:
        raise ValueError(f"object key must be a non-empty string, got {key!r}")
    if key.startswith("/"):
        raise ValueError(f"object key {key!r} is absolute; keys are relative '/'-separated paths")
    if "\\" in key or "\x00" in key:
        raise ValueError(f"object key {key!r} contains a backslash or NUL")
    for seg in key.split("/"):
        if seg in ("", ".", ".."):
            raise ValueError(f"object key {key!r} has an empty, '.' or '..' segment")
    return key


def check_prefix(prefix: str) -> str:
    """Return a safe listing prefix ('' = everything; a trailing '/' is allowed), else raise ValueError."""
    if prefix == "":
        return prefix
    check_key(prefix[:-1] if prefix.endswith("/") else prefix)
    return prefix


def join_key(prefix: str, key: str) -> str:
    """`prefix/key` with exactly one '/' between them ('' prefix: key itself)."""
    prefix = prefix.strip("/")
    return f"{prefix}/{key}" if prefix else key


_io: tuple[int, ThreadPoolExecutor] | None = None


def io_pool() -> ThreadPoolExecutor:
    """Threads for a store's blocking calls (fsync, S3 requests), made in this process (a forked child makes
    its own: a parent's threads do not survive a fork)."""
    global _io
    if _io is None or _io[0] != os.getpid():
        _io = (os.getpid(), ThreadPoolExecutor(max_workers=8, thread_name_prefix="store-io"))
    return _io[1]


@runtime_checkable
class ObjectStore(Protocol):
    """A flat key -> bytes store. Writes are atomic: readers see the old object or the new one, never a
    part."""

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectInfo:
        """Store `data` under `key`, replacing any object there."""
        ...

    def put_many(self, items: Sequence[tuple[str, bytes]], *, keep_cached: bool = True) -> list[ObjectInfo]:
        """Store each (key, data) as put_bytes does, together: a view's ~18 files cost one wait for the disk
        (local) or the network (S3) instead of one each. All stored, or StorageError (some may be stored).
        keep_cached=False: nothing here reads them back soon (a worker's outputs), so a store that caches what
        it writes (the local folder: the page cache) need not keep them."""
        ...

    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectInfo:
        """Store the file at `path` under `key` (multipart upload for big files on S3)."""
        ...

    def get_bytes(self, key: str) -> bytes:
        """The object's content; ObjectNotFoundError when missing."""
        ...

    def get_file(self, key: str, path: str | Path) -> Path:
        """Download the object to `path` (parent folders created); ObjectNotFoundError when missing."""
        ...

    def exists(self, key: str) -> bool:
        """Whether an object is stored under `key`."""
        ...

    def stat(self, key: str) -> ObjectInfo | None:
        """Size (and sha256 when known) of the object, or None when missing."""
        ...

    def delete(self, key: str) -> bool:
        """Remove the object; True if it existed (deleting a missing key is not an error)."""
        ...

    def delete_prefix(self, prefix: str) -> int:
        """Remove every object whose key starts with `prefix`; returns how many."""
        ...

    def list(self, prefix: str = "") -> Iterator[str]:
        """Keys starting with `prefix`, in sorted (byte) order."""
        ...

    def presigned_url(self, key: str, expires_s: int = 3600) -> str:
        """A URL that fetches the object without credentials (S3: pre-signed GET; local: file:// URI)."""
        ...

    def probe(self) -> None:
        """Check the store is there and writable (write and delete a small object); StorageError if not."""
        ...


class PrefixedStore:
    """A view of a store rooted at `prefix`: keys are relative to it, listings strip it."""

    def __init__(self, store: ObjectStore, prefix: str):
        self.store = store
        self.prefix = check_key(prefix.rstrip("/"))

    def _k(self, key: str) -> str:
        return join_key(self.prefix, check_key(key))

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectInfo:
        info = self.store.put_bytes(self._k(key), data, content_type)
        return ObjectInfo(key, info.size, info.sha256)

    def put_many(self, items: Sequence[tuple[str, bytes]], *, keep_cached: bool = True) -> list[ObjectInfo]:
        infos = self.store.put_many([(self._k(key), data) for key, data in items], keep_cached=keep_cached)
        return [ObjectInfo(key, info.size, info.sha256) for (key, _), info in zip(items, infos, strict=True)]

    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectInfo:
        info = self.store.put_file(self._k(key), path, content_type)
        return ObjectInfo(key, info.size, info.sha256)

    def get_bytes(self, key: str) -> bytes:
        try:
            return self.store.get_bytes(self._k(key))
        except ObjectNotFoundError:
            raise ObjectNotFoundError(key) from None

    def get_file(self, key: str, path: str | Path) -> Path:
        try:
            return self.store.get_file(self._k(key), path)
        except ObjectNotFoundError:
            raise ObjectNotFoundError(key) from None

    def exists(self, key: str) -> bool:
        return self.store.exists(self._k(key))

    def stat(self, key: str) -> ObjectInfo | None:
        info = self.store.stat(self._k(key))
        return None if info is None else ObjectInfo(key, info.size, info.sha256)

    def delete(self, key: str) -> bool:
        return self.store.delete(self._k(key))

    def delete_prefix(self, prefix: str) -> int:
        return self.store.delete_prefix(self.prefix + "/" + check_prefix(prefix))

    def list(self, prefix: str = "") -> Iterator[str]:
        cut = len(self.prefix) + 1
        for key in self.store.list(self.prefix + "/" + check_prefix(prefix)):
            yield key[cut:]

    def presigned_url(self, key: str, expires_s: int = 3600) -> str:
        return self.store.presigned_url(self._k(key), expires_s)

    def probe(self) -> None:
        self.store.probe()


def prefixed(store: ObjectStore, prefix: str) -> ObjectStore:
    """A view of `store` rooted at `prefix` (e.g. a job's output root); '' returns the store itself."""
    if not prefix.rstrip("/"):
        return store
    return PrefixedStore(store, prefix)
