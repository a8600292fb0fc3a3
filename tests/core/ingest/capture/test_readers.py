"""Capture readers: each format written in its exact file names and conventions reads back as the same
cameras; bad frames get one message each and the good ones go on; nothing outside the upload is opened."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from services.core.ingest.capture import find_capture
from services.core.ingest.capture.attach import capture_files_beside, capture_near
from services.core.ingest.capture.distortion import distort, undistort
from services.core.ingest.guard.archive import MESH_SUFFIXES
from services.core.ingest.loading import load_space
from services.core.ingest.registry import pack_source
from tests.fixtures.captures import (
    toy_frames,
    write_camera_poses,
    write_colmap,
    write_scannet,
    write_sevenscenes,
    write_transforms,
)

SCENES = Path(__file__).resolve().parents[4] / "../shared/scenes"


def _same_cameras(capture, frames, *, shared_K: bool = False, check_K: bool = True) -> None:
    assert len(capture.frames) == len(frames), capture.problems
    for got, want in zip(capture.frames, frames, strict=True):
        np.testing.assert_allclose(got.camera_to_world, want.camera_to_world, atol=1e-9)
        if check_K:
            np.testing.assert_allclose(got.K, frames[0].K if shared_K else want.K, atol=1e-9)
        assert (got.width, got.height) == want.size
        assert capture.image_path(got).is_file()


def test_sevenscenes_layout(tmp_path):
    frames = toy_frames(5)
    write_sevenscenes(tmp_path, frames)
    cap = find_capture(tmp_path)
    assert cap is not None and cap.format == "7scenes" and not cap.problems
    _same_cameras(cap, frames, shared_K=True)
    assert cap.frames[0].image == "seq-01/frame-000000.color.jpg"


def test_a_capture_is_read_once_per_unchanged_folder_while_kept_and_again_when_a_file_changes(
    tmp_path, monkeypatch
):
    from services.core.ingest.capture import detect

    reads = []
    real = detect.read_sevenscenes
    monkeypatch.setattr(detect, "read_sevenscenes", lambda *a: reads.append(a) or real(*a))
    frames = toy_frames(4)
    d = write_sevenscenes(tmp_path, frames)
    find_capture(tmp_path)
    find_capture(tmp_path)
    assert len(reads) == 2  # outside captures_kept(): every call reads
    with detect.captures_kept():
        first = find_capture(tmp_path)
        with detect.captures_kept():  # nested (a command inside a command): one store
            # the same folder, unchanged: not read again
            assert find_capture(tmp_path) is first and len(reads) == 3
        pose = d / "frame-000002.pose.txt"
        pose.write_text("\n".join(["-inf -inf -inf -inf"] * 4) + "\n")  # a changed file: read again, and seen
        again = find_capture(tmp_path)
        assert len(reads) == 4 and len(again.frames) == 3 and "frame-000002" in again.problems[0]
        pose.unlink()  # a file gone: read again
        assert len(find_capture(tmp_path).frames) == 3 and len(reads) == 5
        for i in range(detect.KEPT_CAPTURES + 1):  # others asked for since: the least recent is dropped
            (tmp_path / f"other{i}").mkdir()
            assert find_capture(tmp_path / f"other{i}") is None
        find_capture(tmp_path)
        assert len(reads) == 6
    assert not detect._kept  # nothing kept once the command is done
    find_capture(tmp_path)
    assert len(reads) == 7


def test_bundlefusion_info_txt_and_lost_frames(tmp_path):
    frames = toy_frames(4)
    d = write_sevenscenes(tmp_path, frames, info_txt=True)
    (d / "frame-000002.pose.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4) + "\n")
    cap = find_capture(tmp_path)
    assert cap.format == "7scenes" and len(cap.frames) == 3
    assert len(cap.problems) == 1 and "frame-000002" in cap.problems[0] and "infinite" in cap.problems[0]
    assert "info.txt" in cap.notes[0]
    np.testing.assert_allclose(cap.frames[0].K, frames[0].K)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize(
    "model,params",
    [
        ("none", ()), ("radial", (0.05,)), ("opencv", (0.1, -0.02, 0.001, -0.002)),
        ("fisheye", (0.05, 0.01, -0.002, 0.0005)),
    ],
)
def test_colmap_models(tmp_path, binary, model, params):
    frames = toy_frames(3, distortion=model, params=params)
    if model == "radial":  # SIMPLE_RADIAL has one focal length
        for f in frames:
            f.K[1, 1] = f.K[0, 0]
    write_colmap(tmp_path, frames, binary=binary)
    cap = find_capture(tmp_path)
    assert cap.format == "colmap" and not cap.problems
    _same_cameras(cap, frames)
    for f in cap.frames:
        assert f.distortion == model and f.distortion_params == pytest.approx(params)
    assert "points3D: 1 sparse points" in cap.notes


def test_colmap_unsupported_model_and_missing_image(tmp_path):
    frames = toy_frames(3)
    model = write_colmap(tmp_path, frames)
    text = (model / "cameras.txt").read_text().splitlines()
    text[-1] = text[-1].split()[0] + " FOV 64 48 50 50 32 24 0.1"
    (model / "cameras.txt").write_text("\n".join(text) + "\n")
    (tmp_path / "images" / f"{frames[0].name}.jpg").unlink()
    cap = find_capture(tmp_path)
    assert len(cap.frames) == 1
    assert any("FOV" in p and "not supported" in p for p in cap.problems)
    assert any("missing" in p for p in cap.problems)


@pytest.mark.parametrize("per_frame,camera_angle", [(False, False), (True, False), (False, True)])
def test_transforms_json(tmp_path, per_frame, camera_angle):
    frames = toy_frames(3, distortion="opencv", params=(0.1, -0.02, 0.001, -0.002, 0.003))
    if not per_frame:
        for f in frames:
            f.K = frames[0].K.copy()
    write_transforms(tmp_path, frames, per_frame=per_frame, camera_angle=camera_angle)
    cap = find_capture(tmp_path)
    assert cap.format == "transforms" and not cap.problems
    _same_cameras(cap, frames)
    assert cap.frames[0].distortion == "opencv"
    assert cap.frames[0].distortion_params == pytest.approx((0.1, -0.02, 0.001, -0.002, 0.003))


def test_transforms_fisheye_and_bad_frames(tmp_path):
    frames = toy_frames(4, distortion="fisheye", params=(0.05, 0.01, -0.002, 0.0005))
    for f in frames:
        f.K = frames[0].K.copy()
    path = write_transforms(tmp_path, frames)
    doc = json.loads(path.read_text())
    doc["frames"][1]["transform_matrix"][0][0] = 3.0  # not a rotation
    doc["frames"][2]["file_path"] = "../../etc/passwd"  # outside the upload
    doc["frames"].append(
        {"file_path": "images/none.png", "transform_matrix": doc["frames"][0]["transform_matrix"]}
    )
    path.write_text(json.dumps(doc))
    cap = find_capture(tmp_path)
    assert [f.name for f in cap.frames] == [doc["frames"][0]["file_path"], doc["frames"][3]["file_path"]]
    assert len(cap.problems) == 3
    assert any("not a rotation" in p for p in cap.problems)
    assert any("outside the capture" in p for p in cap.problems)
    assert any("missing" in p or "no image size" in p for p in cap.problems)
    assert cap.frames[0].distortion == "fisheye"


def test_scannet_export_and_wrong_size(tmp_path):
    frames = toy_frames(4)
    write_scannet(tmp_path, frames)
    (tmp_path / "pose" / "1.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4))
    from PIL import Image

    Image.new("RGB", (10, 10)).save(tmp_path / "color" / "3.jpg")
    (tmp_path / "color" / "3.jpg").rename(tmp_path / "color" / "3.jpg")
    cap = find_capture(tmp_path)
    assert cap.format == "scannet"
    # the wrong-size photo is caught against the shared intrinsics' size? ScanNet gives no size: it is read
    # from each image, so a 10x10 photo is a frame of its own size; frame 1 is lost
    assert [f.name for f in cap.frames] == ["0", "2", "3"]
    assert len(cap.problems) == 1 and "frame 1" in cap.problems[0]


def test_wrong_image_size_is_reported(tmp_path):
    frames = toy_frames(3)
    write_colmap(tmp_path, frames)
    from PIL import Image

    Image.new("RGB", (20, 10)).save(tmp_path / "images" / f"{frames[1].name}.jpg")
    cap = find_capture(tmp_path)
    assert len(cap.frames) == 2 and len(cap.problems) == 1
    assert "20x10" in cap.problems[0] and "64x48" in cap.problems[0]


def test_camera_poses_json(tmp_path):
    frames = toy_frames(3)
    write_camera_poses(tmp_path, frames)
    cap = find_capture(tmp_path)
    assert cap.format == "camera_poses" and not cap.has_photos
    for got, want in zip(cap.frames, frames, strict=True):
        np.testing.assert_allclose(got.camera_to_world, want.camera_to_world, atol=1e-9)
        assert got.image is None


def test_link_out_of_the_upload_is_not_followed(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.jpg").write_bytes(b"not yours")
    up = tmp_path / "upload"
    frames = toy_frames(2)
    write_colmap(up, frames)
    img = up / "images" / f"{frames[0].name}.jpg"
    img.unlink()
    img.symlink_to(outside / "secret.jpg")
    cap = find_capture(up)
    assert len(cap.frames) == 1 and "outside the capture" in cap.problems[0]


def test_no_capture(tmp_path):
    (tmp_path / "scan.ply").write_text("ply\n")
    assert find_capture(tmp_path) is None


def test_in_world_moves_like_the_mesh():
    frames = toy_frames(2)
    from services.core.ingest.capture.model import Capture, CaptureFrame

    cap = Capture("colmap", Path("."), tuple(
        CaptureFrame(f.name, None, None, None, None, "none", (), f.camera_to_world) for f in frames))
    T = np.eye(4)
    T[:3, :3] = 0.01 * np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    T[:3, 3] = [1, 2, 3]
    world = cap.in_world(T)
    for src, w in zip(cap.frames, world.frames, strict=True):
        point_cam = np.array([0.1, -0.2, 2.0, 1.0])
        np.testing.assert_allclose(
            w.camera_to_world[:3, :3] @ w.camera_to_world[:3, :3].T, np.eye(3), atol=1e-12
        )
        # the camera centre moves like a mesh vertex
        np.testing.assert_allclose(w.center, T[:3, :3] @ src.center + T[:3, 3])
        # a point seen along the same ray stays on it
        p_src = src.camera_to_world @ point_cam
        p_world = T @ p_src
        d = np.linalg.inv(w.camera_to_world) @ p_world
        np.testing.assert_allclose(d[:2] / d[2], point_cam[:2] / point_cam[2], atol=1e-12)


@pytest.mark.parametrize(
    "model,params",
    [
        ("radial", (-0.1, 0.02)), ("opencv", (0.1, -0.02, 0.001, -0.002, 0.01)),
        ("fisheye", (0.05, 0.01, -0.002, 0.0005)),
    ],
)
def test_undistort_inverts_distort(model, params):
    xy = np.random.default_rng(0).uniform(-0.6, 0.6, size=(500, 2))
    np.testing.assert_allclose(undistort(model, params, distort(model, params, xy)), xy, atol=1e-9)


def test_real_7scenes_capture_every_frame():
    root = SCENES / "7scenes_redkitchen"
    cap = find_capture(root)
    assert cap.format == "7scenes" and len(cap.frames) == 100 and not cap.problems
    assert {(f.width, f.height) for f in cap.frames} == {(640, 480)}
    np.testing.assert_allclose(cap.frames[0].K, [[585, 0, 320.5], [0, 585, 240.5], [0, 0, 1]])
    want = np.loadtxt(root / "frames" / "frame-000500.pose.txt")
    got = next(f for f in cap.frames if f.name.endswith("frame-000500"))
    # rotation re-orthonormalised (text noise)
    np.testing.assert_allclose(got.camera_to_world, want, atol=1e-3)
    # up from the cameras (right axes horizontal) is within 5 degrees of the recorded gravity
    up = -np.loadtxt(root / "gravity-direction.txt")
    assert np.degrees(np.arccos(cap.mean_up() @ (up / np.linalg.norm(up)))) < 5.0


def test_beside_a_single_mesh_file_a_capture_is_looked_for_only_as_deep_as_the_layouts_go(tmp_path):
    # A scan saved in a busy folder with someone else's project further down (the 7-Scenes layout, 3 folders
    # deep)
    busy = tmp_path / "Downloads"
    busy.mkdir()
    trimesh.creation.box(extents=(4.0, 3.0, 2.5)).export(busy / "scan.ply")
    write_sevenscenes(busy / "projects" / "kitchen", toy_frames(2), folder="frames")
    (busy / "projects" / "taxes.pdf").write_bytes(b"%PDF- not part of any scan")
    scan = busy / "scan.ply"
    assert capture_near(scan) is None and capture_files_beside(scan, MESH_SUFFIXES) == []
    assert load_space(scan, up_axis="+z", unit_scale=1.0).capture is None
    assert pack_source(scan, scan, tmp_path) == scan  # the scan is stored alone: nothing else of the folder
    assert capture_near(busy).format == "7scenes"  # the folder itself, given by the user, is walked deeper
    # Beside a single file, the formats' own layouts are found: COLMAP's sparse/0/ (2 deep), 7-Scenes frames
    # (1)
    for name, write, fmt in (("colmap", write_colmap, "colmap"), ("7scenes", write_sevenscenes, "7scenes")):
        own = tmp_path / name
        write(own, toy_frames(2))
        trimesh.creation.box(extents=(4.0, 3.0, 2.5)).export(own / "scan.ply")
        assert capture_near(own / "scan.ply").format == fmt
        packed = {
            p.relative_to(own).as_posix() for p in capture_files_beside(own / "scan.ply", MESH_SUFFIXES)
        }
        assert "scan.ply" in packed and any(p.endswith(".jpg") for p in packed)
        assert load_space(own / "scan.ply", up_axis="+z", unit_scale=1.0).capture.format == fmt


def test_capture_inside_a_zip(tmp_path):
    frames = toy_frames(3)
    src = tmp_path / "src"
    write_colmap(src, frames)
    (src / "scan.ply").write_text("ply\n")
    zpath = tmp_path / "up.zip"
    with zipfile.ZipFile(zpath, "w") as zf:
        for p in src.rglob("*"):
            if p.is_file():
                zf.write(p, p.relative_to(src).as_posix())
    from services.core.ingest.guard.archive import safe_extract_zip

    safe_extract_zip(zpath, tmp_path / "x")
    cap = find_capture(tmp_path / "x")
    assert cap.format == "colmap" and len(cap.frames) == 3
