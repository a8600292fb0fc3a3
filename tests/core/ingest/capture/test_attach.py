"""A capture found with a scan: attached to the loaded space in its world frame, stored with the scan when the
space is registered (beside a single mesh file too), and found again by the workers after a fetch."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from services.core.ingest.loading import load_space
from services.core.ingest.registry import fetch_space, register_space
from tests.fixtures.captures import toy_frames, write_colmap, write_transforms


def _bunny_with_capture(scenes_dir: Path, folder: Path, writer=write_colmap) -> Path:
    folder.mkdir(parents=True)
    ply = folder / "bunny.ply"
    shutil.copy(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply", ply)
    writer(folder, toy_frames(3))
    return ply


def test_capture_beside_a_mesh_file_is_attached_in_world_frame(scenes_dir, tmp_path):
    ply = _bunny_with_capture(scenes_dir, tmp_path / "scan")
    space = load_space(ply, up_axis="+y")
    assert (
        space.capture is not None and space.capture.frame_space == "world" and len(space.capture.frames) == 3
    )
    src = load_space(ply, up_axis="+y").capture.frames[0]
    T = space.source_to_world
    frames = toy_frames(3)
    np.testing.assert_allclose(src.center, T[:3, :3] @ frames[0].camera_to_world[:3, 3] + T[:3, 3], atol=1e-9)
    assert space.frame_record()["capture"]["frames"] == 3


def test_a_scan_alone_has_no_capture(scenes_dir):
    assert load_space(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply").capture is None


def test_registering_a_mesh_file_stores_its_capture_and_fetch_finds_it(
    db_session, local_store, scenes_dir, tmp_path
):
    ply = _bunny_with_capture(scenes_dir, tmp_path / "scan", writer=write_transforms)
    space = register_space(db_session, local_store, owner="alice", name="bunny_cap", source_path=ply)
    assert space.source_key.endswith(".zip")
    assert space.validation["capture"]["format"] == "transforms"
    fetched = fetch_space(local_store, space, tmp_path / "cache")
    again = load_space(fetched)
    assert again.capture is not None and again.capture.has_photos and len(again.capture.frames) == 3
    assert all(again.capture.image_path(f).is_file() for f in again.capture.frames)
    np.testing.assert_array_equal(again.mesh.faces, load_space(ply).mesh.faces)


def test_cameras_up_checks_the_levelling(scenes_dir):
    kitchen = scenes_dir / "7scenes_redkitchen"
    levelled = load_space(kitchen)
    assert levelled.capture.up_angle_deg < 5.0
    assert not any("check the levelling" in w for w in levelled.warnings)
    wrong = load_space(kitchen, up_axis="+z")  # the scan's z is no up at all
    assert wrong.capture.up_angle_deg > 45.0
    assert any("cameras' up" in w and "check the levelling" in w for w in wrong.warnings)


def test_capture_up_is_levelling_evidence(scenes_dir, tmp_path):
    """The cameras' up goes into the up estimator (issue 17's capture_up evidence): the chosen up agrees with
    it, the opposite candidate is marked down by it, and the result is within 3 degrees of the capture's
    gravity; a mesh without its capture carries no such evidence."""
    kitchen = scenes_dir / "7scenes_redkitchen"
    with_capture = load_space(kitchen)
    up = with_capture.frame_record()["up"]
    assert up["evidence"]["capture_up"] > 0 and up["confidence"] == "high"
    assert min(c["evidence"]["capture_up"] for c in up["candidates"]) < 0
    gravity_up = -np.loadtxt(kitchen / "gravity-direction.txt")
    gravity_up /= np.linalg.norm(gravity_up)
    assert np.degrees(np.arccos(with_capture.up_source @ gravity_up)) < 3.0
    alone = tmp_path / "mesh_only.ply"
    shutil.copy(kitchen / "mesh_tsdf_2cm_from_1000frames.ply", alone)
    assert "capture_up" not in load_space(alone, accept_up_guess=True).frame_record()["up"]["evidence"]
