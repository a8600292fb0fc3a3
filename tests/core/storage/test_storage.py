"""Object storage contract: the local folder and S3 (moto over HTTP, boto3 as for real S3) pass the same
tests."""

from __future__ import annotations

import ctypes
import ctypes.util
import hashlib
import mmap
import os
import secrets
import sys
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import boto3
import pytest

from services.core.storage import (
    LocalStore,
    ObjectNotFoundError,
    ObjectStore,
    StorageError,
    open_store,
    prefixed,
)
from services.core.storage.s3 import S3Store
from tests.conftest import S3Server

BAD_KEYS = ["", "/abs/key", "../up", "a/../b", "a//b", "a/./b", "./a", "a/", "a\\b", "..", "a/.."]


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ObjectStore]:
    """Each backend, empty: a fresh folder, or a fresh prefix in the moto bucket (opened via settings)."""
    if request.param == "local":
        yield open_store((tmp_path / "objects").as_uri())
        return
    s3: S3Server = request.getfixturevalue("s3_server")
    settings = s3.settings(prefix=f"t-{secrets.token_hex(4)}/root")
    st = open_store(settings.storage_url, settings)
    assert isinstance(st, S3Store)
    yield st
    st.delete_prefix("")


def test_round_trip_and_stat(store: ObjectStore) -> None:
    assert isinstance(store, ObjectStore)
    data = b"\x89PNG\r\n" + os.urandom(1000)
    info = store.put_bytes("rgb/c/s/point_0_view_0_domain_rgb.png", data, "image/png")
    assert info.size == len(data) and info.sha256 == hashlib.sha256(data).hexdigest()
    assert store.get_bytes("rgb/c/s/point_0_view_0_domain_rgb.png") == data
    assert store.exists("rgb/c/s/point_0_view_0_domain_rgb.png")
    assert not store.exists("rgb/c/s/point_0_view_1_domain_rgb.png")
    st = store.stat("rgb/c/s/point_0_view_0_domain_rgb.png")
    assert st is not None and st.size == len(data) and st.sha256 == info.sha256
    assert st.key == "rgb/c/s/point_0_view_0_domain_rgb.png"
    assert store.stat("nope") is None
    with pytest.raises(ObjectNotFoundError):
        store.get_bytes("nope")
    with pytest.raises(FileNotFoundError):  # ObjectNotFoundError is a FileNotFoundError
        store.get_bytes("rgb/c")  # a "folder" is not an object
    assert store.put_bytes("empty", b"").size == 0 and store.get_bytes("empty") == b""


def test_overwrite_leaves_one_object(store: ObjectStore) -> None:
    store.put_bytes("a/x.json", b"first")
    store.put_bytes("a/x.json", b"second, longer")
    assert list(store.list("a/")) == ["a/x.json"]
    assert store.get_bytes("a/x.json") == b"second, longer"
    st = store.stat("a/x.json")
    assert st is not None and st.size == len(b"second, longer")


def test_list_is_sorted_and_prefix_is_a_string_prefix(store: ObjectStore) -> None:
    keys = ["b/2", "a/b/c", "a/b1", "a/a", "a-b", "c", "a/b/d/e"]
    for k in keys:
        store.put_bytes(k, k.encode())
    assert list(store.list()) == sorted(keys)
    assert list(store.list("a/")) == ["a/a", "a/b/c", "a/b/d/e", "a/b1"]
    assert list(store.list("a/b")) == ["a/b/c", "a/b/d/e", "a/b1"]
    assert list(store.list("a/b/")) == ["a/b/c", "a/b/d/e"]
    assert list(store.list("zzz/")) == []
    assert list(store.list("a")) == ["a-b", "a/a", "a/b/c", "a/b/d/e", "a/b1"]


def test_delete_and_delete_prefix(store: ObjectStore) -> None:
    for i in range(5):
        store.put_bytes(f"job/rgb/{i}.png", b"x")
        store.put_bytes(f"job/normal/{i}.png", b"y")
    store.put_bytes("jobs-other/keep", b"z")
    assert store.delete("job/rgb/0.png") is True
    assert store.delete("job/rgb/0.png") is False  # missing: not an error
    assert store.delete_prefix("job/rgb/") == 4
    assert list(store.list("job/")) == [f"job/normal/{i}.png" for i in range(5)]
    assert store.delete_prefix("job/") == 5
    assert store.delete_prefix("job/") == 0
    assert list(store.list()) == ["jobs-other/keep"]


def test_big_file_multipart_round_trip(store: ObjectStore, tmp_path: Path) -> None:
    src = tmp_path / "big.bin"
    data = os.urandom(10 * 1024 * 1024 + 12345)  # > 10 MiB: two 8 MiB parts on S3
    src.write_bytes(data)
    info = store.put_file("spaces/1/source.zip", src)
    assert info.size == len(data) and info.sha256 == hashlib.sha256(data).hexdigest()
    out = store.get_file("spaces/1/source.zip", tmp_path / "dl" / "copy.zip")
    assert out.read_bytes() == data
    st = store.stat("spaces/1/source.zip")
    assert st is not None and st.size == len(data) and st.sha256 == info.sha256
    if isinstance(store, S3Store):
        head = store.client.head_object(Bucket=store.bucket, Key=store._k("spaces/1/source.zip"))
        # S3's multipart ETag: md5-of-md5s-<parts>
        assert head["ETag"].strip('"').endswith("-2"), head["ETag"]
    with pytest.raises(ObjectNotFoundError):
        store.get_file("spaces/1/missing.zip", tmp_path / "x")


def test_presigned_url_downloads_without_credentials(store: ObjectStore) -> None:
    store.put_bytes("out/job.json", b'{"ok": true}', "application/json")
    url = store.presigned_url("out/job.json", expires_s=600)
    if isinstance(store, S3Store):
        assert (
            url.startswith("http://127.0.0.1:") and "X-Amz-Signature=" in url and "X-Amz-Expires=600" in url
        )
    else:
        assert url.startswith("file:///")
    with urllib.request.urlopen(url, timeout=10) as resp:  # plain HTTP (or file://), no boto3
        assert resp.read() == b'{"ok": true}'


@pytest.mark.parametrize("key", BAD_KEYS)
def test_bad_keys_refused(store: ObjectStore, key: str, tmp_path: Path) -> None:
    f = tmp_path / "f"
    f.write_bytes(b"1")
    for call in (
        lambda: store.put_bytes(key, b"1"),
        lambda: store.put_file(key, f),
        lambda: store.get_bytes(key),
        lambda: store.get_file(key, tmp_path / "o"),
        lambda: store.exists(key),
        lambda: store.stat(key),
        lambda: store.delete(key),
        lambda: store.presigned_url(key, 60),
    ):
        with pytest.raises(ValueError):
            call()
    if key not in ("", "a/"):  # '' lists everything; a trailing '/' is a folder prefix
        with pytest.raises(ValueError):
            list(store.list(key))
        with pytest.raises(ValueError):
            store.delete_prefix(key)
    assert list(store.list()) == []  # nothing was written anywhere


def test_prefixed_view(store: ObjectStore) -> None:
    view = prefixed(store, "jobs/42/")
    assert prefixed(store, "") is store
    view.put_bytes("rgb/a.png", b"1")
    view.put_bytes("rgb/b.png", b"22")
    store.put_bytes("jobs/420/rgb/a.png", b"not mine")
    assert store.get_bytes("jobs/42/rgb/a.png") == b"1"
    assert list(view.list()) == ["rgb/a.png", "rgb/b.png"]
    assert list(view.list("rgb/b")) == ["rgb/b.png"]
    st = view.stat("rgb/b.png")
    assert st is not None and st.key == "rgb/b.png" and st.size == 2
    with pytest.raises(ObjectNotFoundError) as e:
        view.get_bytes("rgb/c.png")
    assert e.value.key == "rgb/c.png"
    with pytest.raises(ValueError):
        view.get_bytes("../420/rgb/a.png")
    with pytest.raises(ValueError):
        prefixed(store, "/abs")
    nested = prefixed(view, "rgb")
    assert nested.get_bytes("a.png") == b"1"
    assert view.delete_prefix("") == 2
    assert list(store.list()) == ["jobs/420/rgb/a.png"]


def resident_fraction(path: Path) -> float:
    """The fraction of the file's pages in the page cache (mincore over a shared read-only mapping of it)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [
        ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long,
    ]
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p]
    libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    size, page = path.stat().st_size, mmap.PAGESIZE
    pages = (size + page - 1) // page
    with path.open("rb") as f:
        addr = libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, f.fileno(), 0)
        assert addr not in (None, ctypes.c_void_p(-1).value), os.strerror(ctypes.get_errno())
        try:
            vec = ctypes.create_string_buffer(pages)
            assert libc.mincore(addr, size, vec) == 0, os.strerror(ctypes.get_errno())
            return sum(b & 1 for b in vec.raw) / pages
        finally:
            libc.munmap(addr, size)


def filesystem_of(path: Path) -> str:
    """The type of the file system `path` is on (the longest mount point above it in /proc/mounts)."""
    here, best = path.resolve().as_posix().rstrip("/") + "/", ("", "")
    for line in Path("/proc/mounts").read_text().splitlines():
        _, mount, fstype, *_ = line.split()
        if here.startswith(mount.rstrip("/") + "/") and len(mount) >= len(best[0]):
            best = (mount, fstype)
    return best[1]


@pytest.mark.skipif(sys.platform != "linux", reason="mincore and posix_fadvise as Linux has them")
def test_put_many_leaves_files_it_need_not_keep_cached_out_of_the_page_cache(tmp_path: Path) -> None:
    if filesystem_of(tmp_path) in ("tmpfs", "ramfs"):
        pytest.skip("on a file system in memory the cached pages are the files: there is nothing to drop")
    store = LocalStore(tmp_path / "objects")
    data = os.urandom(4 << 20)
    store.put_many([("passes/a.npz", data)])
    store.put_many([("rgb/a.png", data), ("depth/a.png", data[:5000])], keep_cached=False)
    assert resident_fraction(store.path("passes/a.npz")) > 0.9  # written and kept: in the page cache
    assert resident_fraction(store.path("rgb/a.png")) == 0.0  # flushed, then dropped
    assert resident_fraction(store.path("depth/a.png")) == 0.0
    # from the disk
    assert store.get_bytes("rgb/a.png") == data and store.get_bytes("depth/a.png") == data[:5000]


def test_put_many_stores_each_object_as_put_bytes_would(store: ObjectStore) -> None:
    items = [(f"{cue}/c/s/point_0_view_0_domain_{cue}.png", os.urandom(n)) for cue, n in
             (("rgb", 5_000), ("normal", 70_000), ("position", 3_000_000), ("mask_valid", 0))]
    infos = store.put_many(items)
    assert [(i.key, i.size, i.sha256) for i in infos] == [
        (key, len(data), hashlib.sha256(data).hexdigest()) for key, data in items]
    assert all(store.get_bytes(key) == data for key, data in items)
    assert list(store.list()) == sorted(key for key, _ in items)
    view = prefixed(store, "jobs/7")  # a job's output root, as the worker writes through it
    (info,) = view.put_many([("rgb/a.png", b"1")])
    assert info.key == "rgb/a.png" and store.get_bytes("jobs/7/rgb/a.png") == b"1"
    assert store.put_many([]) == []


# ---------------------------------------------------------------------------------------------- backend
# specifics


def test_local_writes_are_atomic_and_leave_no_temp_files(local_store: LocalStore) -> None:
    local_store.put_bytes("a/b.bin", b"x" * 100)
    local_store.put_bytes("a/b.bin", b"y" * 10)
    assert sorted(p.name for p in (local_store.root / "a").iterdir()) == ["b.bin"]
    # an in-flight write (temp file) is not an object
    (local_store.root / "a" / ".c.bin.tmp-0123456789abcdef0123456789abcdef").write_bytes(b"partial")
    assert list(local_store.list()) == ["a/b.bin"]
    assert local_store.path("a/b.bin") == local_store.root / "a" / "b.bin"
    local_store.delete("a/b.bin")
    assert (local_store.root / "a").is_dir()  # still holds the temp file
    assert local_store.presigned_url("a/b.bin").startswith("file://")


def test_local_temp_files_of_killed_writers_are_removed(local_store: LocalStore) -> None:
    local_store.put_bytes("a/b.bin", b"x")
    stale = local_store.root / "a" / "deep" / ".c.png.tmp-0123456789abcdef0123456789abcdef"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"partial")
    lookalike = local_store.root / "a" / ".c.png.tmp-not-a-uuid"  # not ours: kept
    lookalike.write_bytes(b"keep")
    assert local_store.remove_temp_files() == 1
    assert not stale.exists() and lookalike.exists() and local_store.get_bytes("a/b.bin") == b"x"


def test_local_delete_prunes_empty_folders(local_store: LocalStore) -> None:
    local_store.put_bytes("x/y/z/1", b"1")
    local_store.delete("x/y/z/1")
    assert list(local_store.root.iterdir()) == []
    assert local_store.root.is_dir()


def test_s3_stat_of_foreign_object_has_no_sha(s3_server: S3Server) -> None:
    client = boto3.client(
        "s3", endpoint_url=s3_server.endpoint_url, region_name=s3_server.region,
        aws_access_key_id=s3_server.access_key, aws_secret_access_key=s3_server.secret_key,
    )
    client.put_object(Bucket=s3_server.bucket, Key="foreign/obj", Body=b"abc")
    st = S3Store(s3_server.bucket, "foreign", endpoint_url=s3_server.endpoint_url,
                 credentials=(s3_server.access_key, s3_server.secret_key))
    info = st.stat("obj")
    assert info is not None and info.size == 3 and info.sha256 is None
    assert list(st.list()) == ["obj"]
    assert st.delete_prefix("") == 1


def test_open_store_urls(tmp_path: Path, s3_server: S3Server) -> None:
    a = open_store(str(tmp_path / "plain"))
    b = open_store((tmp_path / "uri").as_uri())
    assert isinstance(a, LocalStore) and a.root == tmp_path / "plain"
    assert isinstance(b, LocalStore) and b.root == tmp_path / "uri"
    s = open_store(f"s3://{s3_server.bucket}/p/q", s3_server.settings())
    assert isinstance(s, S3Store) and s.bucket == s3_server.bucket and s.prefix == "p/q"
    with pytest.raises(ValueError, match="unsupported storage URL"):
        open_store("ftp://host/x")
    with pytest.raises(ValueError, match="names a host"):
        open_store("file://host/x")


def test_probe_writes_and_cleans_up(store: ObjectStore) -> None:
    store.probe()
    store.probe()
    assert list(store.list()) == []
    prefixed(store, "jobs/1").probe()  # a view probes the store it is a view of


def test_a_missing_bucket_is_a_named_storage_error(s3_server: S3Server, tmp_path: Path) -> None:
    missing = f"missing-{secrets.token_hex(4)}"
    settings = s3_server.settings()
    st = open_store(f"s3://{missing}/data", settings)
    src = tmp_path / "src.bin"
    src.write_bytes(b"x" * 100)
    calls = {
        "probe": st.probe,
        "put_bytes": lambda: st.put_bytes("a/b", b"x"),
        "put_file": lambda: st.put_file("a/c", src),
        "get_bytes": lambda: st.get_bytes("a/b"),
        "list": lambda: next(iter(st.list("a/")), None),
        "delete": lambda: st.delete("a/b"),
        "delete_prefix": lambda: st.delete_prefix("a/"),
    }
    for name, call in calls.items():
        with pytest.raises(StorageError, match=rf"^the bucket s3://{missing} does not exist$"):
            call()
            pytest.fail(f"{name} did not fail")
    # get_file and exists start with a HEAD, whose 404 cannot tell a missing bucket from a missing key
    assert st.exists("a/b") is False


def test_a_local_store_that_cannot_write_is_a_named_storage_error(tmp_path: Path) -> None:
    st = LocalStore(tmp_path / "objects")
    (st.root / "spaces").write_bytes(b"a file where a folder must go")
    with pytest.raises(StorageError, match=rf"cannot write to the object folder {st.root}: "):
        st.put_bytes("spaces/1/scan.ply", b"ply")
    assert [p.name for p in st.root.iterdir()] == ["spaces"]  # no temp file left behind
    with pytest.raises(StorageError, match=rf"cannot write to the object folder {st.root}: "):
        st.put_many([("rgb/a.png", b"1"), ("spaces/1/scan.ply", b"ply")])  # the second cannot be written
    assert sorted(p.name for p in st.root.iterdir()) == ["rgb", "spaces"] and list(st.list()) == ["spaces"]
    # the first was never renamed in, and its temp file is gone
    assert list((st.root / "rgb").iterdir()) == []
    (st.root / "rgb").rmdir()
    (st.root / "spaces").unlink()
    st.root.rmdir()
    with pytest.raises(StorageError, match="does not exist"):
        st.probe()
    assert not st.root.exists()
