"""Public scan datasets as downloaded: each layout's fixture (exact file names, headers, conventions) loads as
one space whose faces carry the dataset's own class ids, instance ids and class names, in the dataset's frame;
a dataset root becomes its scenes; HM3D's Basis-compressed release is refused naming the one that works."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from services.core.ingest.datasets import find_scenes, scene_mesh_in
from services.core.ingest.loading import LoadedSpace, SpaceError, load_space, resolve_source
from services.core.ingest.registry import pack_source
from tests.fixtures import scan_datasets as ds
from tests.fixtures.scan_datasets import MPCAT40, NYU40, PARTS, REPLICA


def parts_of(space: LoadedSpace) -> np.ndarray:
    """Which fixture part each loaded face lies on (world frame): proves the dataset's frame was applied."""
    return np.array([ds.part_of(c) for c in space.mesh.triangles_center])


def labels_by_part(space: LoadedSpace) -> dict[int, tuple[set[int], set[int]]]:
    assert space.has_semantics and space.face_class is not None and space.face_instance is not None
    part = parts_of(space)
    return {p: (set(space.face_class[part == p].tolist()), set(space.face_instance[part == p].tolist()))
            for p in range(len(PARTS))}


def test_scannet_scene_nyu40_classes_aggregation_instances_and_axis_alignment(tmp_path: Path) -> None:
    folder = ds.write_scannet_scene(tmp_path / "scans")
    assert scene_mesh_in(folder) == folder / "scene0000_00_vh_clean_2.ply"  # not the high-res mesh
    space = load_space(folder)
    np.testing.assert_allclose(space.source_to_world, ds.scannet_alignment(), atol=1e-6)
    np.testing.assert_allclose(space.bounds, [[0, 0, 0], ds.ROOM], atol=1e-5)  # walls back on the axes
    for p, (classes, instances) in labels_by_part(space).items():
        assert classes == {NYU40[PARTS[p]]} and instances == {p + 1}, p
    assert (
        space.class_names is not None
        and space.class_names[22] == "ceiling"
        and space.class_names[7] == "table"
    )
    # the high-resolution mesh, named: labels carried over from the decimated one
    high = load_space(folder / "scene0000_00_vh_clean.ply")
    assert len(high.mesh.faces) == 4 * 14
    for p, (classes, instances) in labels_by_part(high).items():
        assert classes == {NYU40[PARTS[p]]} and instances == {p + 1}, p
    # packed for storage: the label files and the meta file go along, the raw capture (.sens) does not
    packed = pack_source(folder, scene_mesh_in(folder), tmp_path)  # type: ignore[arg-type]
    names = set(zipfile.ZipFile(packed).namelist())
    assert "scene0000_00.sens" not in names and "scene0000_00_vh_clean_2.labels.ply" in names
    again = load_space(packed)
    assert np.array_equal(again.face_class, space.face_class) and np.array_equal(
        again.face_instance, space.face_instance
    )


def test_scannet_axis_alignment_must_be_rigid(tmp_path: Path) -> None:
    folder = ds.write_scannet_scene(tmp_path / "scans")
    meta = folder / "scene0000_00.txt"
    meta.write_text(meta.read_text().replace("axisAlignment = ", "axisAlignment = 2 "))
    with pytest.raises(SpaceError, match="axisAlignment must be 16 numbers"):
        load_space(folder)


def test_scannetpp_segments_anno_with_the_release_class_list(tmp_path: Path) -> None:
    scene = ds.write_scannetpp_scene(tmp_path / "data")
    space = load_space(scene)
    ids = {"ceiling": 1, "floor": 2, "table": 3, "wall": 4}  # metadata/semantic_classes.txt order
    for p, (classes, instances) in labels_by_part(space).items():
        assert classes == {ids[PARTS[p]]} and instances == {p + 1}, p
    assert space.class_names == {1: "ceiling", 2: "floor", 3: "table", 4: "wall"}


def test_hm3d_semantic_glb_and_txt_on_the_plain_release(tmp_path: Path) -> None:
    folder = ds.write_hm3d_scene(tmp_path / "train")
    assert scene_mesh_in(folder) == folder / "TEEsavR23oF.glb"
    space = load_space(folder)
    ids = {"ceiling": 1, "floor": 2, "table": 3, "wall": 4}  # HM3D names categories: numbered in sorted order
    for p, (classes, instances) in labels_by_part(space).items():  # parts_of: +Y up was turned to +Z
        assert classes == {ids[PARTS[p]]} and instances == {p + 1}, p
    assert space.class_names == {1: "ceiling", 2: "floor", 3: "table", 4: "wall"}


def test_hm3d_basis_release_is_refused_naming_the_plain_glb_and_obj(tmp_path: Path) -> None:
    folder = ds.write_hm3d_scene(tmp_path / "train", plain=False)
    for given in (folder, folder / "TEEsavR23oF.basis.glb"):
        with pytest.raises(SpaceError) as e:
            load_space(given)
        assert (
            "Basis Universal" in str(e.value) and "TEEsavR23oF.glb" in str(e.value) and ".obj" in str(e.value)
        )
    # the same check on any glb that requires KHR_texture_basisu, whatever its name
    renamed = tmp_path / "scan.glb"
    renamed.write_bytes((folder / "TEEsavR23oF.basis.glb").read_bytes())
    with pytest.raises(SpaceError, match="KHR_texture_basisu"):
        load_space(renamed)


def test_matterport_house_obj_with_region_labels_in_mpcat40(tmp_path: Path) -> None:
    house = ds.write_matterport_house(tmp_path / "v1" / "scans")
    space = load_space(house)
    assert space.has_texture
    found = labels_by_part(space)
    for p, (classes, instances) in found.items():
        assert classes == {MPCAT40[PARTS[p]][0]} and len(instances) == 1 and 0 not in instances, p
    assert len({next(iter(i)) for _, i in found.values()}) == len(PARTS)  # one instance per object
    assert space.class_names is not None and {space.class_names[i] for i, _ in MPCAT40.values()} == set(
        MPCAT40
    )


def test_replica_quads_with_habitat_semantic_mesh(tmp_path: Path) -> None:
    folder = ds.write_replica_scene(tmp_path)
    assert scene_mesh_in(folder) == folder / "mesh.ply"
    space = load_space(folder)
    for p, (classes, instances) in labels_by_part(space).items():
        assert classes == {REPLICA[PARTS[p]]} and instances == {3 * p + 2}, p
    assert (
        space.class_names is not None and space.class_names[93] == "wall" and space.class_names[40] == "floor"
    )


def test_3rscan_textured_obj_with_annotated_ply(tmp_path: Path) -> None:
    folder = ds.write_3rscan_scene(tmp_path)
    space = load_space(folder)
    assert space.has_texture
    for p, (classes, instances) in labels_by_part(space).items():
        assert classes == {NYU40[PARTS[p]]} and instances == {p + 1}, p
    assert space.class_names is not None and space.class_names[1] == "wall"


def test_gibson_renders_mesh_z_up(tmp_path: Path) -> None:
    folder = ds.write_gibson_building(tmp_path)
    assert resolve_source(folder) == folder / "mesh_z_up.obj"  # not the original-frame mesh.obj beside it
    space = load_space(folder)
    assert not space.has_semantics and space.up_method == "given"
    np.testing.assert_allclose(space.bounds, [[0, 0, 0], ds.ROOM], atol=1e-5)


def test_a_dataset_root_lists_its_scenes_by_id_and_the_refused_ones(tmp_path: Path) -> None:
    scans = tmp_path / "ScanNet" / "scans"
    for scene in ("scene0000_00", "scene0001_01"):
        ds.write_scannet_scene(scans, scene)
    (scans / "notes").mkdir()
    assert [(s.scene_id, s.dataset, s.refused) for s in find_scenes(scans)] == [
        ("scene0000_00", "scannet", None), ("scene0001_01", "scannet", None)]
    split = tmp_path / "hm3d" / "train"
    ds.write_hm3d_scene(split)
    ds.write_hm3d_scene(split, "00801", "HaxA7YrQdEC", plain=False)
    found = find_scenes(tmp_path / "hm3d")
    assert [(s.scene_id, s.refused is None) for s in found] == [
        ("00800-TEEsavR23oF", True), ("00801-HaxA7YrQdEC", False),
    ]
    assert "HaxA7YrQdEC.glb" in (found[1].refused or "")
    mp = find_scenes(tmp_path / "v1" / "scans") if (tmp_path / "v1").exists() else []
    assert mp == []
    ds.write_matterport_house(tmp_path / "v1" / "scans")
    assert [s.scene_id for s in find_scenes(tmp_path / "v1")] == ["17DRP5sb8fy"]
