"""Object storage: `open_store(url)` picks the backend ("file:///abs/path", a plain path,
"s3://bucket/prefix")."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import unquote, urlparse

from services.core.storage.base import (
    ObjectInfo,
    ObjectNotFoundError,
    ObjectStore,
    PrefixedStore,
    StorageError,
    StorageUnavailable,
    check_key,
    prefixed,
    storage_outage,
)
from services.core.storage.local import LocalStore

if TYPE_CHECKING:
    from services.core.settings import Settings

__all__ = [
    "LocalStore",
    "ObjectInfo",
    "ObjectNotFoundError",
    "ObjectStore",
    "PrefixedStore",
    "StorageError",
    "StorageUnavailable",
    "check_key",
    "open_store",
    "prefixed",
    "storage_outage",
]


def open_store(url: str, settings: Settings | None = None, *, s3_attempts: int | None = None) -> ObjectStore:
    """Open the store at `url`; S3 endpoint, region and credentials come from `settings` (default:
    environment). `s3_attempts`: tries of an S3 request through 5xx and throttling (default S3Store's)."""
    parsed = urlparse(url)
    if parsed.scheme == "s3":
        from services.core.settings import get_settings
        from services.core.storage.s3 import S3Store

        s = settings or get_settings()
        creds = None
        if s.aws_access_key_id is not None and s.aws_secret_access_key is not None:
            creds = (s.aws_access_key_id.get_secret_value(), s.aws_secret_access_key.get_secret_value())
        return S3Store(
            parsed.netloc, parsed.path.strip("/"), endpoint_url=s.s3_endpoint_url, region=s.s3_region,
            credentials=creds, **({"max_attempts": s3_attempts} if s3_attempts else {}),
        )
    if parsed.scheme == "file":
        if parsed.netloc not in ("", "localhost"):
            raise ValueError(f"file URL {url!r} names a host; use file:///absolute/path")
        return LocalStore(Path(unquote(parsed.path)))
    if parsed.scheme == "":
        return LocalStore(Path(url))
    raise ValueError(f"unsupported storage URL {url!r}: use file:///abs/path, a path, or s3://bucket/prefix")
