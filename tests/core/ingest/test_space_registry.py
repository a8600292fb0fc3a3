"""Registering spaces: validation before storage, packing, and fetching back (local folder and real S3)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from services.core.db.models import Space
from services.core.ingest.errors import SpaceError
from services.core.ingest.loading import load_space
from services.core.ingest.registry import fetch_space, register_space
from services.core.storage import open_store


def _banana(scenes_dir: Path) -> Path:
    return scenes_dir / "ycb_banana" / "textured_simple_reoriented.obj"


def test_obj_is_packed_with_its_mtl_and_texture_and_fetched_back(
    db_session, local_store, scenes_dir, tmp_path
):
    space = register_space(
        db_session, local_store, owner="alice", name="banana", source_path=_banana(scenes_dir)
    )
    assert space.source_key == f"spaces/{space.id}/textured_simple_reoriented.zip"
    with zipfile.ZipFile(local_store.root / space.source_key) as zf:
        assert sorted(zf.namelist()) == ["texture_map.png", "textured_simple_reoriented.mtl",
                                         "textured_simple_reoriented.obj"]
    assert space.has_texture and not space.has_semantics and space.face_count > 1000
    mesh_path = fetch_space(local_store, space, tmp_path / "cache")
    again = load_space(mesh_path)
    original = load_space(_banana(scenes_dir))
    # same faces in the same order and the same world frame: rendered pixels line up with the plan
    np.testing.assert_array_equal(again.mesh.faces, original.mesh.faces)
    np.testing.assert_allclose(again.mesh.vertices, original.mesh.vertices)
    np.testing.assert_allclose(np.array(space.source_to_world), original.source_to_world)
    assert again.has_texture
    assert fetch_space(local_store, space, tmp_path / "cache") == mesh_path  # cached, no second download


def test_ply_round_trips_through_real_s3(db_session, s3_server, scenes_dir, tmp_path):
    store = open_store(s3_server.settings(prefix="reg").storage_url, s3_server.settings(prefix="reg"))
    ply = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    space = register_space(db_session, store, owner="bob", name="bunny", source_path=ply)
    assert space.source_key.endswith("/bun_zipper_res2.ply")
    assert store.stat(space.source_key).size == ply.stat().st_size
    fetched = fetch_space(store, space, tmp_path / "cache")
    assert fetched.read_bytes() == ply.read_bytes()


def test_refused_space_leaves_no_row_and_no_object(db_session, local_store, tmp_path):
    bad = tmp_path / "nan.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nthis is not a mesh\n")
    with pytest.raises(SpaceError):
        register_space(db_session, local_store, owner="alice", name="nan", source_path=bad)
    assert db_session.query(Space).filter_by(name="nan").count() == 0
    assert list(local_store.list("spaces/")) == []


def test_duplicate_and_bad_names_are_refused(db_session, local_store, scenes_dir):
    ply = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    register_space(db_session, local_store, owner="alice", name="bunny", source_path=ply)
    with pytest.raises(SpaceError, match="already exists"):
        register_space(db_session, local_store, owner="alice", name="bunny", source_path=ply)
    with pytest.raises(SpaceError, match="not a valid name"):
        register_space(db_session, local_store, owner="alice", name="../evil", source_path=ply)
    # another tenant may reuse the name
    register_space(db_session, local_store, owner="carol", name="bunny", source_path=ply)
