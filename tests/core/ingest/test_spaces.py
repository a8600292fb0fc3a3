"""services.core.ingest.loading: finding, validating, levelling and labelling spaces."""

from __future__ import annotations

import hashlib
import json
import stat
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from services.core.ingest.errors import SpaceError
from services.core.ingest.frame.resolve import rotation_to_z
from services.core.ingest.guard.archive import resolve_source
from services.core.ingest.loading import load_space
from tests.fixtures import scenes


@pytest.fixture(scope="module")
def shared_scenes(scenes_dir: Path) -> Path:
    """The real scans, `<repo>/../shared/scenes` (tests/conftest.py fails clearly when missing)."""
    return scenes_dir


def _rot(axis: str, deg: float) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(
        np.radians(deg), {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[axis]
    )


def _export(mesh: trimesh.Trimesh, path: Path) -> Path:
    mesh.export(path)
    return path


def _textured_quad_obj(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (4, 4), (200, 10, 10)).save(folder / "tex.png")
    (folder / "quad.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
    (folder / "quad.obj").write_text(
        "mtllib quad.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    )
    return folder / "quad.obj"


# --- resolving sources -------------------------------------------------------------------------


def test_resolve_file_folder_and_errors(tmp_path: Path) -> None:
    obj = _textured_quad_obj(tmp_path / "one")
    assert resolve_source(obj) == obj
    assert resolve_source(tmp_path / "one") == obj
    (tmp_path / "two").mkdir()
    _export(scenes.box_room(), tmp_path / "two" / "a.ply")
    _export(scenes.box_room(), tmp_path / "two" / "b.obj")
    with pytest.raises(SpaceError, match=r"2 meshes.*a\.ply.*b\.obj"):
        resolve_source(tmp_path / "two")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SpaceError, match="holds no mesh"):
        resolve_source(tmp_path / "empty")
    (tmp_path / "x.stl").write_text("solid x\nendsolid x\n")
    with pytest.raises(SpaceError, match="unsupported file type '.stl'"):
        resolve_source(tmp_path / "x.stl")
    with pytest.raises(SpaceError, match="no such file"):
        resolve_source(tmp_path / "missing.obj")


def test_zip_with_textured_obj_loads(tmp_path: Path) -> None:
    src = _textured_quad_obj(tmp_path / "src")
    z = tmp_path / "quad.zip"
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
        for f in src.parent.iterdir():
            zf.write(f, f"scan/{f.name}")
    space = load_space(z)
    assert space.has_texture
    assert space.face_count == 2
    assert space.source_path == z  # extracted to a temporary folder, removed after loading
    kept = load_space(z, extract_dir=tmp_path / "x")
    assert kept.source_path == (tmp_path / "x" / "scan" / "quad.obj").resolve()
    assert kept.checksum == hashlib.sha256(src.read_bytes()).hexdigest()


def _zip_with(path: Path, name: str, data: bytes, *, symlink: bool = False) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        info = zipfile.ZipInfo(name)
        info.compress_type = zipfile.ZIP_DEFLATED
        if symlink:
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
        zf.writestr(info, data)
    return path


@pytest.mark.parametrize(
    ("member", "symlink", "message"),
    [
        ("../evil.obj", False, r"climbs out of the archive"),
        ("a/../../evil.obj", False, r"climbs out of the archive"),
        ("/etc/evil.obj", False, r"absolute path"),
        ("C:/evil.obj", False, r"absolute path"),
        ("link.obj", True, r"symbolic link"),
    ],
)
def test_hostile_zip_members_refused(tmp_path: Path, member: str, symlink: bool, message: str) -> None:
    z = _zip_with(tmp_path / "bad.zip", member, b"v 0 0 0\n", symlink=symlink)
    with pytest.raises(SpaceError, match=message):
        resolve_source(z, tmp_path / "out")
    assert not (tmp_path / "evil.obj").exists()


def test_zip_bomb_refused(tmp_path: Path) -> None:
    z = _zip_with(tmp_path / "bomb.zip", "big.obj", b"\0" * (4 << 20))
    with pytest.raises(SpaceError, match="zip bomb"):
        resolve_source(z, tmp_path / "out")
    ok = _zip_with(tmp_path / "ok.zip", "room.obj", b"\0" * 1000)
    with pytest.raises(SpaceError, match="uncompressed size 1000 bytes exceeds the limit 100"):
        resolve_source(ok, tmp_path / "out2", max_total_bytes=100)
    (tmp_path / "junk.zip").write_bytes(b"not a zip")
    with pytest.raises(SpaceError, match="not a readable zip"):
        resolve_source(tmp_path / "junk.zip", tmp_path / "out3")


# --- validation ----------------------------------------------------------------------------------


def test_invalid_meshes_refused_clearly(tmp_path: Path) -> None:
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(SpaceError, match="empty|no faces|holds no triangle mesh"):
        load_space(tmp_path / "empty.obj")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(SpaceError, match="no faces|empty|holds no triangle mesh"):
        load_space(tmp_path / "points.obj")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(SpaceError, match="NaN or infinite"):
        load_space(tmp_path / "nan.obj")
    room = _export(scenes.box_room(), tmp_path / "room.ply")
    with pytest.raises(SpaceError, match=r"km\).*unit_scale"):
        load_space(room, unit_scale=2000.0)  # a 6-unit room at 2 km per unit is 12 km across
    with pytest.raises(SpaceError, match=r"less than 1 mm.*unit_scale"):
        load_space(room, unit_scale=1e-4)
    (tmp_path / "garbage.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(SpaceError, match="garbage.ply"):
        load_space(tmp_path / "garbage.ply")
    with pytest.raises(SpaceError, match="up_axis"):
        load_space(room, up_axis="up")


# --- frames and up axis --------------------------------------------------------------------------


def test_face_order_and_source_to_world_match_trimesh_load(tmp_path: Path) -> None:
    src = _export(scenes.pillar_room().apply_transform(_rot("x", 90)), tmp_path / "room.obj")
    space = load_space(src, unit_scale=0.5)
    ref = trimesh.load(src, force="mesh")
    assert space.face_count == len(ref.faces)
    np.testing.assert_array_equal(space.mesh.faces, ref.faces)
    world = trimesh.transform_points(ref.vertices, space.source_to_world)
    np.testing.assert_allclose(space.mesh.vertices, world, atol=1e-12)
    np.testing.assert_allclose(space.source_to_world[:3, 3], 0.0)  # no translation
    np.testing.assert_allclose(np.linalg.det(space.source_to_world[:3, :3]), 0.5**3)
    np.testing.assert_allclose(space.bounds, space.mesh.bounds)
    np.testing.assert_allclose(space.mesh.extents, [3.0, 2.0, 1.35], atol=1e-9)


@pytest.mark.parametrize(
    "rotation",
    [
        np.eye(4),
        _rot("x", 90),  # +Z -> -Y
        _rot("x", -90),  # +Z -> +Y, the glTF convention
        _rot("y", 90) @ _rot("z", 30),
        _rot("x", 180),  # upside down
        _rot("x", 90) @ _rot("y", 7),  # tilted 7 degrees, then axes swapped
        _rot("z", 40) @ _rot("x", 4) @ _rot("y", -3),  # a slightly tilted scan
    ],
)
def test_levelling_undoes_a_known_rotation(tmp_path: Path, rotation: np.ndarray) -> None:
    room = scenes.furnished_room()
    src = _export(room.copy().apply_transform(rotation), tmp_path / "room.ply")
    space = load_space(src)
    assert space.up_method == "floor"
    # world up is the room's original up: source_to_world undoes the rotation up to a turn about +Z
    M = space.source_to_world[:3, :3] @ rotation[:3, :3]
    # PLY stores float32 coordinates: levelling is exact up to that rounding
    np.testing.assert_allclose(M @ [0, 0, 1.0], [0, 0, 1.0], atol=1e-6)
    floor = space.mesh.triangles_center[space.mesh.face_normals[:, 2] > 0.99]
    zs = floor[:, 2]
    assert np.ptp(zs[zs < zs.min() + 0.5]) < 1e-5  # the floor is level


def test_up_fallbacks_and_explicit_axis(tmp_path: Path, shared_scenes: Path) -> None:
    # a closed empty box is symmetric (floor = ceiling): the file convention decides
    box = scenes.box_room(size=(6.0, 2.7, 4.0))  # y-up: 2.7 high, floor and ceiling 6 x 4
    obj = _export(box.copy(), tmp_path / "box.obj")
    sp = load_space(obj)
    assert sp.up_method == "convention-tie"
    np.testing.assert_allclose(sp.up_source, [0, 1, 0])
    np.testing.assert_allclose(sp.source_to_world[:3, :3], _rot("x", 90)[:3, :3], atol=1e-15)
    given = load_space(obj, up_axis="-x")
    assert given.up_method == "given"
    np.testing.assert_allclose(given.source_to_world[:3, :3] @ [-1, 0, 0], [0, 0, 1], atol=1e-15)
    bunny = load_space(shared_scenes / "stanford_bunny" / "bun_zipper_res2.ply")
    assert bunny.up_method == "base"  # the flat base of the scan, not the PLY +Z convention
    np.testing.assert_allclose(bunny.up_source, [0, 1, 0])
    banana = load_space(shared_scenes / "ycb_banana" / "textured_simple_reoriented.obj")
    assert banana.up_method == "convention"
    np.testing.assert_allclose(banana.up_source, [0, 1, 0])
    sphere = _export(trimesh.creation.icosphere(subdivisions=2), tmp_path / "ball.ply")
    ball = load_space(sphere)
    assert ball.up_method == "convention"
    np.testing.assert_allclose(ball.up_source, [0, 0, 1])
    # the warning says what decided, not an empty margin and angle
    (note,) = [w for w in ball.warnings if "low confidence" in w]
    assert "file format's convention decided" in note and "None" not in note
    (note,) = [w for w in sp.warnings if "low confidence" in w]
    assert "floor and ceiling look alike" in note and "None" not in note


@pytest.mark.parametrize(
    "up", [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [0.1, -0.2, 0.97]]
)
def test_rotation_to_z(up: list[float]) -> None:
    u = np.array(up) / np.linalg.norm(up)
    R = rotation_to_z(u)
    np.testing.assert_allclose(R @ u, [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)


# --- real scans ----------------------------------------------------------------------------------


def test_real_scans_load(shared_scenes: Path) -> None:
    bunny = load_space(shared_scenes / "stanford_bunny" / "bun_zipper_res2.ply")
    assert bunny.face_count == 16301
    assert not bunny.has_texture and not bunny.has_vertex_colors and not bunny.has_semantics
    assert bunny.checksum == "8faa052bb08cf1625eec97b6508baceee11eec9cf28f83f6a9d4547ab15d7761"
    np.testing.assert_allclose(bunny.mesh.extents, [0.156, 0.121, 0.153], atol=2e-3)  # +Y became +Z
    banana = load_space(shared_scenes / "ycb_banana")
    assert banana.has_texture and banana.face_count == 15728
    assert banana.checksum == "ee31f11cd1d5b07d84e50761873abe7fbc53de76b5b01fa286935198ad0d49cb"


# --- semantics -----------------------------------------------------------------------------------


def _labelled_scene(mixed: bool) -> tuple[np.ndarray, list[list[int]], np.ndarray, np.ndarray]:
    v = np.array([
        [0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0],  # floor quad 0..3
        [0, 0, 2], [4, 0, 2], [4, 3, 2], [0, 3, 2],  # ceiling 4..7
        [1, 1, 1], [2, 1, 1], [2.5, 1.8, 1], [1.5, 2.5, 1], [0.8, 1.8, 1],  # pentagon 8..12
    ], dtype=float)
    if mixed:  # a quad, two triangles and a pentagon
        polys = [[0, 1, 2, 3], [0, 4, 1], [1, 4, 5], [8, 9, 10, 11, 12]]
    else:  # Replica: quads only (trimesh reads binary PLY lists of one length only)
        polys = [[0, 1, 2, 3], [4, 7, 6, 5], [0, 4, 5, 1], [8, 9, 10, 11]]
    return v, polys, np.array([3, 7, 7, 9]), np.array([100, 200, 201, 300])


@pytest.mark.parametrize(("binary", "mixed"), [(False, True), (False, False), (True, False)])
def test_ply_face_labels_follow_triangulation(tmp_path: Path, binary: bool, mixed: bool) -> None:
    v, polys, cls, inst = _labelled_scene(mixed)
    path = tmp_path / "labelled.ply"
    scenes.write_ply_with_labels(path, v, polys, cls, inst, binary=binary)
    space = load_space(path, up_axis="+z")
    ref = trimesh.load(path, force="mesh")
    assert space.has_semantics
    assert space.face_class is not None and space.face_instance is not None
    n_tri = sum(len(p) - 2 for p in polys)
    assert space.face_class.dtype == np.int32 and len(space.face_class) == len(ref.faces) == n_tri
    # each triangle carries the label of the polygon its vertices come from
    for t, tri in enumerate(ref.triangles):
        owner = [k for k, p in enumerate(polys) if all(np.isclose(v[p], x).all(axis=1).any() for x in tri)]
        assert len(owner) == 1
        assert space.face_class[t] == cls[owner[0]]
        assert space.face_instance[t] == inst[owner[0]]


def test_replica_object_id_and_info_semantic(tmp_path: Path) -> None:
    v, polys, _, _ = _labelled_scene(mixed=False)
    path = tmp_path / "mesh.ply"
    scenes.write_ply_with_labels(
        path, v, polys, None, np.array([0, 1, 1, 2]), instance_name="object_id", binary=True
    )
    only_instances = load_space(path, up_axis="+z")
    assert only_instances.face_instance is not None and only_instances.face_class is None
    assert not only_instances.has_semantics
    (tmp_path / "info_semantic.json").write_text(json.dumps({"id_to_label": [5, 6, 40]}))
    labelled = load_space(path, up_axis="+z")
    assert labelled.has_semantics
    np.testing.assert_array_equal(np.unique(labelled.face_class), [5, 6, 40])
    np.testing.assert_array_equal(labelled.face_class[labelled.face_instance == 1], 6)


def test_unlabelled_ply_has_no_semantics(tmp_path: Path) -> None:
    space = load_space(_export(scenes.box_room(), tmp_path / "plain.ply"))
    assert space.face_class is None and space.face_instance is None and not space.has_semantics


def test_vertex_colours_detected(tmp_path: Path) -> None:
    m = scenes.box_room()
    m.visual.vertex_colors = np.tile([10, 200, 30, 255], (len(m.vertices), 1))
    space = load_space(_export(m, tmp_path / "coloured.ply"))
    assert space.has_vertex_colors and not space.has_texture
