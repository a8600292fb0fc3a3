"""`omnidata generate` on dataset roots as downloaded (ScanNet/scans/, hm3d/train/): one job, one space per
scene named by its scene id, a refused scene summarised (the others rendered), and the semantic cues carrying
the dataset's own ids, checked pixel by pixel against an independent ray cast of the fixture room."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from services.worker.passes import ViewGeometry
from tests.fixtures import scan_datasets as ds
from tests.fixtures.cli import omnidata
from tests.fixtures.raycast import raycast

SPEC = """
cues: [rgb, segment_semantic, segment_instance, point_info]
points: {count: 2, min_views: 1, max_views: 1}
views: {resolution: 48}
"""


def room_world() -> trimesh.Trimesh:
    vertices = ds.room_quads().reshape(-1, 3)
    quads = np.arange(28).reshape(7, 4)
    return trimesh.Trimesh(
        vertices, np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]), process=False
    )


def check_view(out: Path, space: str, point_info: Path, expected_class: dict[str, int],
               expected_instance: dict[int, int]) -> None:
    """The rendered class / instance of each pixel is the dataset's id of the part the reference ray hits."""
    info = json.loads(point_info.read_text())
    geometry = ViewGeometry(
        np.asarray(info["world_to_camera"], dtype=np.float64), float(info["field_of_view_rads"]),
        int(info["resolution"]),
    )
    cast = raycast(room_world(), geometry)
    stem = point_info.name.replace("_domain_point_info.json", "")
    semantic = np.array(
        Image.open(out / "segment_semantic" / "datasets" / space / f"{stem}_domain_segment_semantic.png")
    )
    instance = np.array(
        Image.open(out / "segment_instance" / "datasets" / space / f"{stem}_domain_segment_instance.png")
    )
    part = np.where(cast.hit, ds.triangle_part()[np.maximum(cast.tri, 0)], -1)
    want_class = np.vectorize(lambda p: expected_class[ds.PARTS[p]] if p >= 0 else 0)(part)
    want_instance = np.vectorize(lambda p: expected_instance[p] if p >= 0 else 0)(part)
    agree = (semantic == want_class) & (instance.astype(np.int64) == want_instance)
    assert agree.mean() > 0.97, (space, stem, agree.mean())  # pixels on a part boundary may differ
    assert len(np.unique(semantic[cast.hit])) >= 1 and set(np.unique(semantic)) <= set(
        expected_class.values()
    ) | {0}


@pytest.mark.slow
@pytest.mark.bpy
def test_generate_on_dataset_roots(tmp_path: Path) -> None:
    scans, split = tmp_path / "ScanNet" / "scans", tmp_path / "hm3d" / "train"
    for scene in ("scene0000_00", "scene0001_01"):
        ds.write_scannet_scene(scans, scene)
    ds.write_hm3d_scene(split)
    ds.write_hm3d_scene(split, "00801", "HaxA7YrQdEC", plain=False)  # only the Basis release: refused
    roots = [scans, split, tmp_path / "v1" / "scans", tmp_path / "replica", tmp_path / "3RScan",
             tmp_path / "scannetpp" / "data", tmp_path / "gibson"]
    ds.write_matterport_house(roots[2])
    ds.write_replica_scene(roots[3])
    ds.write_3rscan_scene(roots[4])
    ds.write_scannetpp_scene(roots[5])
    ds.write_gibson_building(roots[6])  # unlabelled: refused for the semantic cues, the others go on
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)
    out = tmp_path / "out"
    res = omnidata("generate", *roots, "--out", out, "--spec", spec, "--workers", 1, "--name", "datasets",
                   "--seed", 3, timeout=900)
    assert res.returncode == 0, res.stderr
    assert "refused scene(s)" in res.stderr and "00801-HaxA7YrQdEC: HaxA7YrQdEC.basis.glb" in res.stderr
    assert "HaxA7YrQdEC.glb" in res.stderr and "spaces: 100%" in res.stderr  # the bar over spaces
    assert "Allensville: cue 'segment_semantic' needs semantic labels" in res.stderr
    job = json.loads((out / "job.json").read_text())
    hm3d_ids = {"ceiling": 1, "floor": 2, "table": 3, "wall": 4}  # sorted category names
    in_order = {p: p + 1 for p in range(7)}
    expectations = {
        "scene0000_00": (ds.NYU40, in_order),
        "scene0001_01": (ds.NYU40, in_order),
        "00800-TEEsavR23oF": (hm3d_ids, in_order),
        "17DRP5sb8fy": (
            {n: i for n, (i, _) in ds.MPCAT40.items()}, {0: 1, 1: 2, 2: 3, 4: 4, 6: 5, 3: 6, 5: 7},
        ),
        "room_0": (ds.REPLICA, {p: 3 * p + 2 for p in range(7)}),
        "f62fd5fd-9a3f-2f44-883a-1e5cf819608e": (ds.NYU40, in_order),
        "0a5c013435": (hm3d_ids, in_order),  # metadata/semantic_classes.txt happens to list them sorted
    }
    assert sorted(job["spaces"]) == sorted(expectations)
    views = 0
    for space, (classes, instances) in expectations.items():
        for info in sorted((out / "point_info" / "datasets" / space).glob("*.json")):
            check_view(out, space, info, classes, instances)
            views += 1
    assert views >= 3
