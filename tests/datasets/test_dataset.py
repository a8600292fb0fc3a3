"""OmnidataDataset on a real generated job: units checked against independent files, S3 through moto, splits,
multi-view items, the released starter layout, and torch's DataLoader with its default collate."""

from __future__ import annotations

import json
import pickle
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.core.domain.camera import camera_center, project
from services.core.domain.cues import UnknownCueError, default_cues
from services.core.storage import ObjectStore, open_store
from services.core.storage.s3 import S3Store
from services.datasets import DatasetIntegrityError, OmnidataDataset, assign_splits, camera_of, split_of
from services.datasets.source import ViewRecord
from services.datasets.splits import split_csv_text
from tests.conftest import S3Server

CUES = default_cues(has_semantics=False)
RES = 32
# the contract of the issue: dtype and channel count of every cue the banana job has
CONTRACT: dict[str, tuple[Any, int]] = {
    "rgb": (np.float32, 3), "normal": (np.float32, 3), "depth_zbuffer": (np.float32, 1),
    "depth_euclidean": (np.float32, 1), "mask_valid": (np.bool_, 1), "reshading": (np.float32, 1),
    "principal_curvature": (np.float32, 2), "edge_texture": (np.float32, 1),
    "edge_occlusion": (np.float32, 1), "keypoints2d": (np.float32, 1), "keypoints3d": (np.float32, 1),
    "segment_unsup2d": (np.int64, 1), "segment_unsup25d": (np.int64, 1), "fragments": (np.int64, 1),
    "position": (np.float32, 3),
}
JSON_CUES = {"point_info", "nonfixated", "vanishing_points"}


def test_every_cue_has_its_dtype_shape_and_units(small_job: Path) -> None:
    ds = OmnidataDataset(small_job, CUES)
    assert len(ds) == 4 and ds.incomplete_views == 0
    assert set(CUES) == set(CONTRACT) | JSON_CUES
    for i in range(len(ds)):
        item = ds[i]
        for cue, (dtype, channels) in CONTRACT.items():
            assert item[cue].dtype == dtype and item[cue].shape == (channels, RES, RES), cue
        for cue in JSON_CUES:
            assert isinstance(item[cue], str) and json.loads(item[cue])
        valid = item["mask_valid"][0]
        assert valid.any() and not valid.all()  # an object on empty background
        assert 0 <= item["rgb"].min() and item["rgb"].max() <= 1
        depth, euclid = item["depth_zbuffer"][0], item["depth_euclidean"][0]
        assert np.array_equal(np.isnan(depth), ~valid) and not (depth[valid] < 0).any()
        assert (euclid[valid] >= depth[valid] - 1 / 512).all()  # the centre is never nearer than the plane
        n = item["normal"][:, valid]
        np.testing.assert_allclose(np.linalg.norm(n, axis=0), 1, atol=1e-5)
        assert np.isnan(item["normal"][:, ~valid]).all()
        assert (item["fragments"][0][~valid] == -1).all() and (item["fragments"][0][valid] >= 0).all()
        assert np.isnan(item["position"][:, ~valid]).all()
        assert (item["keypoints3d"] >= 0).all() and (item["keypoints3d"] <= 1).all()
        k = item["principal_curvature"][:, valid]
        assert np.abs(k).max() <= 1 / 0.03 + 1e-3  # clipped to 1/curvature_clip_m
        assert (item["space"], item["point"], item["view"]) == ("ycb_banana", i // 2, i % 2)


def test_depth_in_metres_matches_world_positions(small_job: Path) -> None:
    """depth_zbuffer (PNG) against the camera-frame z of position (EXR, another render pass) and the pose."""
    ds = OmnidataDataset(small_job, ["depth_zbuffer", "depth_euclidean", "position", "mask_valid"])
    for i in range(len(ds)):
        item = ds[i]
        valid = item["mask_valid"][0]
        xyz = item["position"][:, valid].T.astype(np.float64)
        w2c = item["world_to_camera"].astype(np.float64)
        z = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        np.testing.assert_allclose(item["depth_zbuffer"][0][valid], z[:, 2], atol=1.5 / 512)
        dist = np.linalg.norm(xyz - camera_center(w2c), axis=1)
        np.testing.assert_allclose(item["depth_euclidean"][0][valid], dist, atol=1.5 / 512)


def test_camera_matches_point_info(small_job: Path) -> None:
    ds = OmnidataDataset(small_job, ["point_info"])
    for i in range(len(ds)):
        item = ds[i]
        info = json.loads(item["point_info"])
        f = (RES / 2) / np.tan(info["field_of_view_rads"] / 2)
        np.testing.assert_allclose(item["K"], [[f, 0, RES / 2], [0, f, RES / 2], [0, 0, 1]], rtol=1e-6)
        w2c = item["world_to_camera"].astype(np.float64)
        np.testing.assert_allclose(w2c[:3, :3] @ w2c[:3, :3].T, np.eye(3), atol=1e-6)
        np.testing.assert_allclose(camera_center(w2c), info["camera_location"], atol=1e-5)
        uv, z = project(np.array([info["point_location"]]), item["K"].astype(np.float64), w2c)
        assert z[0] > 0 and (0 <= uv).all() and (uv < RES).all()  # the fixated point is in view
        # the released components have no K / world_to_camera: the Blender pose gives the same matrices
        bare = {k: v for k, v in info.items() if k not in ("K", "world_to_camera")}
        K2, w2c2 = camera_of(bare)
        np.testing.assert_allclose(K2, item["K"], rtol=1e-6)
        np.testing.assert_allclose(w2c2, item["world_to_camera"], atol=1e-5)


def test_multi_view_items_share_their_point(small_job: Path) -> None:
    ds = OmnidataDataset(small_job, ["rgb", "depth_zbuffer"], views_per_sample=2)
    assert len(ds) == 4  # each view is an anchor once
    single = OmnidataDataset(small_job, ["rgb", "depth_zbuffer"])
    for i in range(len(ds)):
        item = ds[i]
        assert item["rgb"].shape == (2, 3, RES, RES) and item["K"].shape == (2, 3, 3)
        assert sorted(item["view"].tolist()) == [0, 1]
        for j, v in enumerate(item["view"].tolist()):
            alone = single[item["point"] * 2 + v]
            assert alone["point"] == item["point"] and alone["view"] == v
            assert np.array_equal(alone["rgb"], item["rgb"][j])
            assert np.array_equal(alone["world_to_camera"], item["world_to_camera"][j])
    assert len(OmnidataDataset(small_job, ["rgb"], views_per_sample=3)) == 0  # points have 2 views


def _starter_tree(job: Path, dest: Path, spaces: list[str]) -> Path:
    """The job's files re-laid as a released Omnidata component: no manifest or job.json, component 'replica',
    'normals' folder, point_info without our K / world_to_camera, each space a copy of the banana."""
    for src in job.glob("*/tiny/ycb_banana/*"):
        cue = src.parts[-4]
        folder = "normals" if cue == "normal" else cue
        for space in spaces:
            target = dest / folder / "replica" / space / src.name
            target.parent.mkdir(parents=True, exist_ok=True)
            if cue == "point_info":
                info = json.loads(src.read_text())
                target.write_text(
                    json.dumps({k: v for k, v in info.items() if k not in ("K", "world_to_camera")})
                )
            else:
                shutil.copyfile(src, target)
    return dest


def test_reads_the_released_starter_layout(small_job: Path, tmp_path: Path) -> None:
    root = _starter_tree(small_job, tmp_path / "starter", ["frl_apartment_0", "room_1"])
    ds = OmnidataDataset(root, ["rgb", "normal", "depth_zbuffer", "point_info", "nonfixated"])
    ours = OmnidataDataset(small_job, ["rgb", "normal", "depth_zbuffer"])
    assert len(ds) == 8 and {v.component for v in ds.views} == {"replica"}
    assert [(v.space, v.point, v.view) for v in ds.views[:4]] == [
        ("frl_apartment_0", p, v) for p in (0, 1) for v in (0, 1)
    ]
    for i in range(4):
        a, b = ds[i], ours[i]
        for cue in ("rgb", "normal", "depth_zbuffer", "K"):
            np.testing.assert_array_equal(a[cue], b[cue])
        np.testing.assert_allclose(a["world_to_camera"], b["world_to_camera"], atol=1e-5)
        assert json.loads(a["nonfixated"])["point_idx"] == a["point"]  # per-point file given to each view


def test_splits_by_space_are_deterministic(small_job: Path, tmp_path: Path) -> None:
    spaces = [f"space_{i:02d}" for i in range(12)]
    root = _starter_tree(small_job, tmp_path / "many", spaces)
    want = assign_splits(spaces, seed=5)
    parts = {}
    for split in ("train", "val", "test"):
        ds = OmnidataDataset(root, ["rgb"], split=split, split_seed=5)
        parts[split] = {v.space for v in ds.views}
        assert parts[split] == {s for s, name in want.items() if name == split}
    assert set.union(*parts.values()) == set(spaces) and sum(map(len, parts.values())) == len(spaces)
    # a fresh interpreter (other hash seed) agrees: nothing depends on Python's str hash
    code = ("import json; from services.datasets import assign_splits; "
            f"print(json.dumps(assign_splits({spaces!r}, seed=5)))")
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        cwd=Path(__file__).resolve().parents[2], env={"PYTHONHASHSEED": "123", "PATH": "/usr/bin"},
    )
    assert json.loads(out.stdout) == want
    # a space keeps its split when others join, and the ratios hold on many spaces
    assert assign_splits(spaces + ["new_a", "new_b"], seed=5)["space_03"] == want["space_03"]
    many = [split_of(f"s{i}", seed=1) for i in range(4000)]
    assert abs(many.count("train") / 4000 - 0.8) < 0.03 and abs(many.count("val") / 4000 - 0.1) < 0.02
    # an Omnidata split CSV decides instead
    csv = tmp_path / "train_val_test_replica.csv"
    csv.write_text(split_csv_text({"space_00": "val", "space_01": "val", "space_02": "train"}))
    assert {v.space for v in OmnidataDataset(root, ["rgb"], split="val", split_csv=csv).views} == {
        "space_00", "space_01",
    }


class RecordingStore:
    """An ObjectStore that records what is read and whether anything is listed."""

    def __init__(self, store: ObjectStore):
        self.store, self.read, self.listed = store, [], False

    def __getattr__(self, name: str) -> Any:
        return getattr(self.store, name)

    def get_bytes(self, key: str) -> bytes:
        self.read.append(key)
        return self.store.get_bytes(key)

    def list(self, prefix: str = "") -> Any:
        self.listed = True
        return self.store.list(prefix)


def _upload(job: Path, store: ObjectStore) -> None:
    for f in sorted(job.rglob("*")):
        rel = f.relative_to(job).as_posix()
        if f.is_file() and not rel.startswith((".omnidata", "_")):
            store.put_bytes(rel, f.read_bytes())


def test_s3_reads_only_the_manifests_keys_and_checks_sha256(small_job: Path, s3_server: S3Server) -> None:
    settings = s3_server.settings(prefix="datasets/jobs/7")
    s3 = open_store(settings.storage_url, settings)
    assert isinstance(s3, S3Store)
    _upload(small_job, s3)
    s3.put_bytes("rgb/tiny/ycb_banana/stray.png", b"not listed in the manifest")
    rec = RecordingStore(s3)
    ds = OmnidataDataset(rec, CUES, verify_sha256=True)  # type: ignore[arg-type]
    local = OmnidataDataset(small_job, CUES)
    manifest = [json.loads(x) for x in (small_job / "manifest.jsonl").read_text().splitlines()]
    listed = {o["key"] for e in manifest for o in e["outputs"].values()} | {"manifest.jsonl", "job.json"}
    for i in range(len(ds)):
        a, b = ds[i], local[i]
        for cue in CONTRACT:
            np.testing.assert_array_equal(a[cue], b[cue])
    assert (
        not rec.listed
        and set(rec.read) <= listed
        and listed - {"job.json", "manifest.jsonl"} <= set(rec.read)
    )
    # the same through a URL (what users type), and a changed object is caught
    by_url = OmnidataDataset(settings.storage_url, ["depth_zbuffer"], settings=settings, verify_sha256=True)
    np.testing.assert_array_equal(by_url[0]["depth_zbuffer"], local[0]["depth_zbuffer"])
    # what a spawned DataLoader worker gets: it opens its own client
    copy = pickle.loads(pickle.dumps(by_url))
    assert copy._store is None and np.array_equal(
        copy[1]["depth_zbuffer"], local[1]["depth_zbuffer"], equal_nan=True
    )
    s3.put_bytes("depth_zbuffer/tiny/ycb_banana/point_0_view_0_domain_depth_zbuffer.png", b"\x89PNG broken")
    with pytest.raises(DatasetIntegrityError, match="point_0_view_0_domain_depth_zbuffer.png: sha256"):
        by_url[0]
    s3.delete("manifest.jsonl")
    with pytest.raises(FileNotFoundError, match="manifest"):
        OmnidataDataset(settings.storage_url, ["rgb"], settings=settings)
    s3.delete_prefix("")


def test_torch_dataloader_default_collate(small_job: Path) -> None:
    import torch  # the dev extra installs it (`pip install -e '.[torch]'` for users)
    from torch.utils.data import DataLoader

    ds = OmnidataDataset(small_job, ["rgb", "depth_zbuffer", "mask_valid", "segment_unsup2d", "point_info"])
    # spawn: the dataset is pickled into the worker, which reopens its store
    loader = DataLoader(ds, batch_size=2, num_workers=1, multiprocessing_context="spawn")
    batches = list(loader)
    assert len(batches) == 2
    b = batches[1]
    assert b["rgb"].dtype == torch.float32 and tuple(b["rgb"].shape) == (2, 3, RES, RES)
    assert b["mask_valid"].dtype == torch.bool and b["segment_unsup2d"].dtype == torch.int64
    assert tuple(b["K"].shape) == (2, 3, 3) and tuple(b["world_to_camera"].shape) == (2, 4, 4)
    assert b["space"] == ["ycb_banana"] * 2 and b["point"].tolist() == [1, 1] and b["view"].tolist() == [0, 1]
    assert len(b["point_info"]) == 2 and json.loads(b["point_info"][0])["view_id"] == 0
    depth = b["depth_zbuffer"]
    assert torch.equal(torch.isnan(depth), ~b["mask_valid"]) and bool((depth[b["mask_valid"]] > 0).all())
    np.testing.assert_array_equal(depth[1].numpy(), ds[3]["depth_zbuffer"])
    multi = next(iter(DataLoader(OmnidataDataset(small_job, ["rgb"], views_per_sample=2), batch_size=3)))
    assert tuple(multi["rgb"].shape) == (3, 2, 3, RES, RES) and tuple(multi["view"].shape) == (3, 2)


def test_bad_arguments_are_refused_with_the_reason(small_job: Path, tmp_path: Path) -> None:
    with pytest.raises(UnknownCueError, match="known cues"):
        OmnidataDataset(small_job, ["rgb", "depht"])
    with pytest.raises(ValueError, match=r"unknown space\(s\) \['nope'\]"):
        OmnidataDataset(small_job, ["rgb"], spaces=["nope"])
    with pytest.raises(ValueError, match="split must be one of"):
        OmnidataDataset(small_job, ["rgb"], split="training")
    with pytest.raises(ValueError, match="views_per_sample"):
        OmnidataDataset(small_job, ["rgb"], views_per_sample=0)
    with pytest.raises(ValueError, match="split ratios"):
        OmnidataDataset(small_job, ["rgb"], split="train", split_ratios=(0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match=r"segment_semantic are not in this dataset"):
        OmnidataDataset(small_job, ["rgb", "segment_semantic"])
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        OmnidataDataset(tmp_path / "missing", ["rgb"])
    ds = OmnidataDataset(small_job, ["rgb"])
    with pytest.raises(IndexError):
        ds[len(ds)]
    assert isinstance(ds.views[0], ViewRecord) and ds.views[0].key == "ycb_banana/point_0_view_0"
