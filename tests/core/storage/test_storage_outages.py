"""Store failures that pass (a full disk, an S3 endpoint answering 5xx) are told apart from those that do not,
on real parts: a full tmpfs for the folder, a loopback endpoint answering 503 for S3. Temp files of killed
writers are swept."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import boto3
import pytest
from botocore.config import Config

from services.core.storage import LocalStore, StorageError, StorageUnavailable, storage_outage
from services.core.storage.s3 import S3Store
from tests.conftest import S3Server
from tests.fixtures.small_disk import fill, small_tmpfs

TMP_NAME = ".{}.tmp-0123456789abcdef0123456789abcdef"


@pytest.fixture()
def full_store(tmp_path: Path) -> Iterator[tuple[LocalStore, Path]]:
    """A LocalStore on a 16 MiB tmpfs holding one object, then filled by a ballast file (returned)."""
    with small_tmpfs(tmp_path / "disk", 16) as disk:
        store = LocalStore(disk)
        store.put_bytes("a/kept.bin", b"kept")
        yield store, fill(disk)


def temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob(".*.tmp-*")]


def test_a_full_folder_fails_writes_with_storage_full_and_leaves_nothing(full_store) -> None:
    store, ballast = full_store
    for write in (lambda: store.put_bytes("b/one.png", b"x" * 200_000),
                  lambda: store.put_many([("b/two.png", b"y" * 100_000), ("b/three.png", b"z" * 100_000)])):
        with pytest.raises(StorageUnavailable, match="storage full: no space left in the object folder"):
            write()
    with pytest.raises(StorageUnavailable, match="storage full"):
        store.probe()
    assert temp_files(store.root) == [] and list(store.list("b/")) == []
    assert store.get_bytes("a/kept.bin") == b"kept"
    ballast.unlink()  # space back: the probe passes, writes go through
    store.probe()
    store.put_bytes("b/one.png", b"x" * 200_000)


def test_a_folder_that_takes_the_probe_but_not_a_view_is_full(tmp_path: Path) -> None:
    with small_tmpfs(tmp_path / "disk", 16) as disk:
        store = LocalStore(disk)
        ballast = fill(disk)
        os.truncate(ballast, os.path.getsize(ballast) - (1 << 20))  # 1 MiB back: bytes fit, views hardly
        store.put_bytes("small", b"ok")
        with pytest.raises(StorageUnavailable, match=r"MiB left in the object folder"):
            store.probe()


def test_outage_is_found_through_causes() -> None:
    try:
        try:
            raise StorageUnavailable("storage full: x")
        except StorageUnavailable as inner:
            raise RuntimeError("wrapped") from inner
    except RuntimeError as outer:
        assert str(storage_outage(outer)) == "storage full: x"
    assert storage_outage(StorageError("no permission")) is None and storage_outage(ValueError()) is None


class _Answer503(BaseHTTPRequestHandler):
    def _reply(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        if length:
            self.rfile.read(length)
        body = b"<Error><Code>ServiceUnavailable</Code><Message>Reduce your request rate.</Message></Error>"
        self.send_response(503)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_GET = do_PUT = do_HEAD = do_POST = do_DELETE = _reply

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture()
def endpoint_503() -> Iterator[str]:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Answer503)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()


def _client(endpoint: str, s3: S3Server):
    return boto3.client("s3", endpoint_url=endpoint, region_name=s3.region, aws_access_key_id=s3.access_key,
                        aws_secret_access_key=s3.secret_key,
                        config=Config(retries={"max_attempts": 1, "mode": "standard"},
                                      s3={"addressing_style": "path"}))


def test_s3_5xx_and_no_answer_are_outages_but_a_missing_bucket_is_not(endpoint_503: str,
                                                                      s3_server: S3Server) -> None:
    down = S3Store(s3_server.bucket, "p", client=_client(endpoint_503, s3_server))
    answered = r"storage unavailable: s3://\S+ answered 503 \(ServiceUnavailable\)"
    with pytest.raises(StorageUnavailable, match=answered):
        down.put_bytes("rgb/a.png", b"x")
    with pytest.raises(StorageUnavailable):
        down.probe()
    gone = S3Store(s3_server.bucket, "p", client=_client("http://127.0.0.1:9", s3_server))  # nothing listens
    with pytest.raises(StorageUnavailable, match="did not answer"):
        gone.put_bytes("rgb/a.png", b"x")
    missing = S3Store("no-such-bucket-here", "p", client=_client(s3_server.endpoint_url, s3_server))
    with pytest.raises(StorageError, match="does not exist") as err:
        missing.put_bytes("rgb/a.png", b"x")
    assert not isinstance(err.value, StorageUnavailable)


# ------------------------------------------------------------------------------------------- temp files swept


def _temp(store: LocalStore, key: str, age_s: float = 0.0) -> Path:
    folder, _, name = key.rpartition("/")
    path = store.root / folder / TMP_NAME.format(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"partial")
    if age_s:
        then = time.time() - age_s
        os.utime(path, (then, then))
    return path


def test_deleting_a_prefix_removes_the_temp_files_of_its_keys(tmp_path: Path) -> None:
    store = LocalStore(tmp_path / "objects")
    store.put_bytes("jobs/1/rgb/a.png", b"a")
    mine = [_temp(store, "jobs/1/rgb/b.png"), _temp(store, "jobs/1/normal/deep/c.png")]
    other = _temp(store, "jobs/10/rgb/b.png")  # another job whose key shares the characters "jobs/1"
    assert store.delete_prefix("jobs/1/") == 1
    assert not any(p.exists() for p in mine) and other.exists()
    assert not (store.root / "jobs" / "1").exists()  # folders pruned once emptied


def test_stale_temp_files_are_swept_and_fresh_ones_kept(tmp_path: Path) -> None:
    store = LocalStore(tmp_path / "objects")
    stale = _temp(store, "rgb/a.png", age_s=3600)
    fresh = _temp(store, "rgb/b.png")
    assert store.remove_temp_files(older_than_s=600) == 1
    assert not stale.exists() and fresh.exists()
