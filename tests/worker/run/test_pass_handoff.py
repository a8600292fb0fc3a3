"""The pass set a renderer hands to the processes that derive its view: the raw form `generate` writes and
the store's .npz read back alike, and a torn file or a raw one of another run read as missing (its view is
rendered again)."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.storage import LocalStore, StorageUnavailable
from services.worker.passes import ViewGeometry, ViewPasses
from services.worker.run.pass_handoff import RawPassSets, StoredPassSets, read_pass_set
from tests.fixtures.small_disk import fill, small_tmpfs

KEY = "_cache/passes/room/point_0_view_1.npz"
RUN = "9f1c"
ARRAYS = ("depth_z", "rgb", "normal_world", "face_index", "face_class", "face_instance", "curvature",
          "photo_coverage")


def _passes(n: int = 24) -> ViewPasses:
    rng = np.random.default_rng(0)
    w2c = np.hstack([np.eye(3), rng.normal(size=(3, 1))])
    return ViewPasses(
        geometry=ViewGeometry(world_to_camera=w2c, fov=0.9, resolution=n),
        depth_z=rng.random((n, n), dtype=np.float32), rgb=rng.integers(0, 255, (n, n, 3), dtype=np.uint8),
        normal_world=rng.random((n, n, 3), dtype=np.float32),
        face_index=rng.integers(0, 2**32 - 1, (n, n), dtype=np.uint32),
        face_class=rng.integers(-1, 40, (n, n), dtype=np.int32), face_instance=None,
        curvature=rng.random((n, n, 2), dtype=np.float32), photo_coverage=rng.random((n, n)) > 0.5,
    )


def test_both_forms_read_back_every_array_and_the_camera(tmp_path):
    store = LocalStore(tmp_path)
    sent = _passes()
    for sets in (RawPassSets(store, RUN), StoredPassSets(store)):
        info = sets.put(KEY, sent)
        data = store.get_bytes(KEY)
        assert info.size == len(data)
        got = sets.read(data)
        assert got is not None
        for name in ARRAYS:
            a, b = getattr(sent, name), getattr(got, name)
            assert (a is None and b is None) or (a.dtype == b.dtype and np.array_equal(a, b)), name
        assert np.array_equal(got.geometry.world_to_camera, sent.geometry.world_to_camera)
        assert (got.geometry.fov, got.geometry.resolution) == (0.9, 24)
    got.depth_z[0, 0] = -1.0  # the cues may write into what they read: the arrays are the reader's own


def test_a_torn_pass_set_reads_as_none_and_the_raw_one_is_written_whole_or_not_at_all(tmp_path):
    store = LocalStore(tmp_path)
    RawPassSets(store, RUN).put(KEY, _passes())
    whole = store.get_bytes(KEY)
    assert read_pass_set(whole, RUN) is not None
    for cut in (len(whole) // 2, 20, 5):
        assert read_pass_set(whole[:cut], RUN) is None
    assert read_pass_set(_passes().to_bytes()[:1000]) is None
    assert [p.name for p in store.path(KEY).parent.iterdir()] == [store.path(KEY).name]  # no temp file left


def test_a_raw_pass_set_on_a_full_disk_is_a_storage_outage_and_leaves_nothing(tmp_path):
    with small_tmpfs(tmp_path / "out", 16) as out:
        store = LocalStore(out)
        ballast = fill(out)
        with pytest.raises(StorageUnavailable):  # the job waits for its store (a task failure it is not)
            RawPassSets(store, RUN).put(KEY, _passes(512))
        assert not store.path(KEY).parent.exists() or not list(store.path(KEY).parent.iterdir())
        ballast.unlink()
        key = RawPassSets(store, RUN).put(KEY, _passes(512)).key
        assert read_pass_set(store.get_bytes(key), RUN) is not None


def test_a_raw_pass_set_is_read_only_by_the_run_that_wrote_it(tmp_path):
    """Unflushed, a set a machine crash left may hold zeros where its data was: a later run (a resumed job)
    renders the view again rather than trust it; the store's .npz (flushed, checksummed) any run reads."""
    store = LocalStore(tmp_path)
    RawPassSets(store, RUN).put(KEY, _passes())
    data = store.get_bytes(KEY)
    assert RawPassSets(store, RUN).read(data) is not None
    assert RawPassSets(store, "another run").read(data) is None
    assert StoredPassSets(store).read(data) is None
    assert read_pass_set(data) is None
    StoredPassSets(store).put(KEY, _passes())
    assert RawPassSets(store, "another run").read(store.get_bytes(KEY)) is not None
