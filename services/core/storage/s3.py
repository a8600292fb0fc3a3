"""Object store on S3 (or any S3-compatible endpoint: MinIO, moto) through boto3."""

from __future__ import annotations

import hashlib
import mimetypes
import os
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import boto3
from boto3.exceptions import S3UploadFailedError
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

from services.core.storage.base import (
    PROBE_KEY,
    ObjectInfo,
    ObjectNotFoundError,
    StorageError,
    StorageUnavailable,
    check_key,
    check_prefix,
    io_pool,
    join_key,
    sha256_file,
)

MULTIPART_THRESHOLD = 8 * 1024 * 1024  # bytes; S3's minimum part size is 5 MiB
_NOT_FOUND = {"404", "NoSuchKey", "NotFound"}


_session_lock = threading.Lock()
_sessions: dict[int, boto3.session.Session] = {}


def _boto_session() -> boto3.session.Session:
    """One boto3 session per process: creating clients from it reuses the loaded service models (~0.3 s
    each)."""
    with _session_lock:  # boto3 sessions are not thread-safe while creating clients
        pid = os.getpid()  # a forked child (Celery prefork) builds its own
        if pid not in _sessions:
            _sessions.clear()
            _sessions[pid] = boto3.session.Session()
        return _sessions[pid]


def _missing(e: ClientError) -> bool:
    return str(e.response.get("Error", {}).get("Code")) in _NOT_FOUND


def _code(e: Exception) -> str:
    if isinstance(e, ClientError):
        return str(e.response.get("Error", {}).get("Code"))
    cause = e.__context__  # S3UploadFailedError wraps the ClientError of the part that failed
    return _code(cause) if isinstance(cause, ClientError) else ""


def _status(e: BaseException | None) -> int:
    """The HTTP status of the S3 reply behind `e` (0: none, e.g. the endpoint did not answer)."""
    if isinstance(e, ClientError):
        return int(e.response.get("ResponseMetadata", {}).get("HTTPStatusCode") or 0)
    return _status(e.__context__) if e is not None and e.__context__ is not e else 0


_THROTTLED = {"SlowDown", "Throttling", "ThrottlingException", "RequestTimeout", "ServiceUnavailable",
              "InternalError"}


def _passing(e: Exception) -> bool:
    """A failure of the endpoint that passes (5xx, throttling, no answer), not of the request (4xx)."""
    if isinstance(e, BotoCoreError):  # connection refused or reset, timeouts: nothing answered
        return True
    return _status(e) >= 500 or _code(e) in _THROTTLED


class S3Store:
    """Keys live under `prefix` in `bucket`; the sha256 of each object is kept in its metadata."""

    def __init__(
        self,
        bucket: str,
        prefix: str = "",
        *,
        endpoint_url: str | None = None,
        region: str = "us-east-1",
        credentials: tuple[str, str] | None = None,
        client: Any = None,  # a boto3 S3 client (boto3 builds its clients at run time: untyped)
        max_attempts: int = 10,
    ):
        if not bucket:
            raise ValueError("S3Store needs a bucket name")
        self.bucket = bucket
        self.prefix = check_key(prefix.strip("/")) if prefix.strip("/") else ""
        if client is None:
            config = Config(
                region_name=region,
                signature_version="s3v4",
                # throttling and 5xx are retried with backoff (10 tries: up to about a minute)
                retries={"max_attempts": max_attempts, "mode": "standard"},
                max_pool_connections=32,
                connect_timeout=10,
                read_timeout=120,
                # MinIO/moto endpoints have no per-bucket DNS names
                s3={"addressing_style": "path" if endpoint_url else "auto"},
            )
            kwargs: dict[str, str | Config | None] = {"endpoint_url": endpoint_url, "config": config}
            if credentials is not None:
                kwargs["aws_access_key_id"], kwargs["aws_secret_access_key"] = credentials
            session = _boto_session()
            with _session_lock:
                client = session.client("s3", **kwargs)
        self.client = client
        self.transfer = TransferConfig(
            multipart_threshold=MULTIPART_THRESHOLD, multipart_chunksize=MULTIPART_THRESHOLD,
            max_concurrency=4,
        )

    def __repr__(self) -> str:
        return f"S3Store(s3://{self.bucket}/{self.prefix})"

    def _k(self, key: str) -> str:
        return join_key(self.prefix, check_key(key))

    def _strip(self, full: str) -> str:
        return full[len(self.prefix) + 1 :] if self.prefix else full

    @contextmanager
    def _failures(self, doing: str) -> Iterator[None]:
        """Turn a failed S3 call (`doing`: "write to", "read from") into a StorageError naming the bucket and
        the problem. A missing object is not a failure: callers turn it into ObjectNotFoundError first."""
        try:
            yield
        except (ClientError, S3UploadFailedError, BotoCoreError) as e:
            code = _code(e)
            where = f"s3://{self.bucket}"
            if code in ("NoSuchBucket", "404"):
                problem = f"the bucket {where} does not exist"
            elif code in ("AccessDenied", "403", "AllAccessDisabled"):
                problem = f"no permission to {doing} {where}"
            elif _passing(e):
                status = _status(e)
                answer = f"answered {status} ({code})" if status else f"did not answer ({type(e).__name__})"
                raise StorageUnavailable(f"storage unavailable: {where} {answer} to a {doing.split()[0]}: "
                                         f"{str(e).splitlines()[0][:200]}") from e
            else:
                problem = f"cannot {doing} {where}: {type(e).__name__}: {str(e).splitlines()[0][:200]}"
            raise StorageError(problem) from e

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectInfo:
        digest = hashlib.sha256(data).hexdigest()
        with self._failures("write to"):
            self.client.put_object(
                Bucket=self.bucket,
                Key=self._k(key),
                Body=data,
                ContentType=content_type or mimetypes.guess_type(key)[0] or "application/octet-stream",
                Metadata={"sha256": digest},
            )
        return ObjectInfo(key, len(data), digest)

    def put_many(self, items: Sequence[tuple[str, bytes]], *, keep_cached: bool = True) -> list[ObjectInfo]:
        """The PUTs in flight together (the client is thread-safe), so a view waits for one round trip, not
        ~18. Nothing is cached here: keep_cached changes nothing."""
        return list(io_pool().map(lambda item: self.put_bytes(*item), items))

    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectInfo:
        path = Path(path)
        digest = sha256_file(path)
        extra = {
            "ContentType": content_type or mimetypes.guess_type(key)[0] or "application/octet-stream",
            "Metadata": {"sha256": digest},
        }
        with self._failures("write to"):
            self.client.upload_file(
                str(path), self.bucket, self._k(key), ExtraArgs=extra, Config=self.transfer
            )
        return ObjectInfo(key, path.stat().st_size, digest)

    def get_bytes(self, key: str) -> bytes:
        with self._failures("read from"):
            try:
                resp = self.client.get_object(Bucket=self.bucket, Key=self._k(key))
            except ClientError as e:
                if _missing(e):
                    raise ObjectNotFoundError(key) from None
                raise
            data: bytes = resp["Body"].read()
        return data

    def get_file(self, key: str, path: str | Path) -> Path:
        dest = Path(path)
        dest.parent.mkdir(parents=True, exist_ok=True)
        with self._failures("read from"):
            try:
                # s3transfer downloads to a temporary name and renames, so `dest` is never half-written
                self.client.download_file(self.bucket, self._k(key), str(dest), Config=self.transfer)
            except ClientError as e:
                if _missing(e):
                    raise ObjectNotFoundError(key) from None
                raise
        return dest

    def _head(self, key: str) -> dict[str, Any] | None:  # boto3's head_object reply
        with self._failures("read from"):
            try:
                head: dict[str, Any] = self.client.head_object(Bucket=self.bucket, Key=self._k(key))
                return head
            except ClientError as e:
                if _missing(e):
                    return None
                raise

    def exists(self, key: str) -> bool:
        return self._head(key) is not None

    def stat(self, key: str) -> ObjectInfo | None:
        """Size, and the sha256 recorded at upload (None for objects written by other tools)."""
        head = self._head(key)
        if head is None:
            return None
        return ObjectInfo(key, int(head["ContentLength"]), head.get("Metadata", {}).get("sha256"))

    def delete(self, key: str) -> bool:
        existed = self.exists(key)
        with self._failures("delete from"):
            self.client.delete_object(Bucket=self.bucket, Key=self._k(key))
        return existed

    def delete_prefix(self, prefix: str) -> int:
        n = 0
        batch: list[str] = []
        for key in self.list(prefix):
            batch.append(self._k(key))
            if len(batch) == 1000:  # DeleteObjects takes at most 1000 keys
                n += self._delete_many(batch)
                batch = []
        if batch:
            n += self._delete_many(batch)
        return n

    def _delete_many(self, full_keys: list[str]) -> int:
        with self._failures("delete from"):
            resp = self.client.delete_objects(
                Bucket=self.bucket, Delete={"Objects": [{"Key": k} for k in full_keys], "Quiet": True}
            )
        errors = resp.get("Errors", [])
        if errors:
            raise StorageError(f"S3 refused to delete {len(errors)} object(s) from s3://{self.bucket}, "
                               f"first: {errors[0]}")
        return len(full_keys)

    def list(self, prefix: str = "") -> Iterator[str]:
        check_prefix(prefix)
        full = join_key(self.prefix, prefix) if prefix else (self.prefix + "/" if self.prefix else "")
        paginator = self.client.get_paginator("list_objects_v2")
        with self._failures("list"):  # pages are fetched as the caller iterates: failures surface here
            for page in paginator.paginate(Bucket=self.bucket, Prefix=full):
                for obj in page.get("Contents", []):  # S3 lists in UTF-8 byte order, which is sorted order
                    yield self._strip(obj["Key"])

    def presigned_url(self, key: str, expires_s: int = 3600) -> str:
        """Pre-signed GET URL valid for `expires_s` seconds."""
        url: str = self.client.generate_presigned_url(
            "get_object", Params={"Bucket": self.bucket, "Key": self._k(key)}, ExpiresIn=int(expires_s)
        )
        return url

    def probe(self) -> None:
        """The bucket exists and takes a write (a small object under the prefix, deleted again)."""
        with self._failures("write to"):
            self.client.head_bucket(Bucket=self.bucket)
            self.client.put_object(Bucket=self.bucket, Key=self._k(PROBE_KEY), Body=b"ok")
            self.client.delete_object(Bucket=self.bucket, Key=self._k(PROBE_KEY))
