"""Gravity and units of scans in any orientation and unit (services.core.ingest.frame.gravity, through
load_space too)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy import sparse

from services.core.ingest.errors import SpaceError, UpAmbiguous
from services.core.ingest.frame.gravity import estimate_up, plane_families
from services.core.ingest.frame.unit_evidence import UnitError, choose_unit_scale
from services.core.ingest.loading import load_space
from tests.fixtures import rotation_corpus as corpus
from tests.fixtures import scenes


@pytest.fixture(scope="module")
def rooms(scenes_dir: Path) -> list[corpus.Room]:
    rng = np.random.default_rng(3)
    return [corpus.icl_room(scenes_dir, faces=6000), corpus.synthetic_room(rng, "noisy"),
            corpus.synthetic_room(rng, "clean", noise_m=0.0)]


def test_rotation_corpus_levelled_and_units_right(rooms: list[corpus.Room]) -> None:
    """>= 50 random rotations per room (plus the 24 axis-aligned ones) in mm, cm, inches and metres."""
    flipped = []
    for case in corpus.cases(rooms, n_random=50, seed=11):
        est = estimate_up(case.mesh, ".ply")
        err = corpus.up_error_deg(est.up, case.up)
        assert est.method == "floor", (case.room, case.kind)
        units = choose_unit_scale(est.storey_height, float(case.mesh.extents.max()))
        assert units.scale == case.scale, (case.room, units)
        if case.kind == "axis" and float(case.up.sum()) < 0 and err > 177.0:
            # exported upside down on an axis with no ceiling: exporters put up on the positive axis, and one
            # plane is a floor or a ceiling alike (up_evidence: mirror), so the file's axis is taken
            assert est.decision is not None and "mirror" in est.decision.best.terms, (case.room, est.record())
            flipped.append(case.room)
            continue
        assert err < 3.0, (case.room, case.kind, err)
        if case.kind == "axis" and case.room in ("clean", "icl_livingroom"):
            # planar floors on an axis give that axis exactly, no rounding noise
            np.testing.assert_array_equal(est.up, np.round(case.up))
    assert "icl_livingroom" not in flipped  # a room with its ceiling keeps its floor, upside down or not


def test_plane_families_find_tilted_walls_and_floor() -> None:
    R = trimesh.transformations.rotation_matrix(np.radians(37), [1, 1, 0.3])
    room = scenes.box_room(size=(6.0, 4.0, 2.7)).apply_transform(R)
    fams = plane_families(room.face_normals, room.area_faces)
    assert len(fams) == 3
    want = [R[:3, :3] @ e for e in np.eye(3)]
    for axis, _ in fams:
        assert max(abs(float(axis @ w)) for w in want) > 1 - 1e-9


def test_the_histogram_smoothing_pairs_are_the_bins_within_six_degrees_antipodes_folded() -> None:
    """The neighbour matrix found through the bin tree is the defined one: |a.b| > cos 6 degrees over all
    pairs."""
    from services.core.ingest.frame.direction_bins import BINS, bin_neighbours

    found = bin_neighbours()
    bins = BINS
    defined = np.abs(bins @ bins.T) > np.cos(np.radians(6.0))
    np.testing.assert_array_equal(found.toarray() != 0, defined)
    assert found.has_sorted_indices and set(found.data) == {1.0}
    hist = np.random.default_rng(0).random(len(bins))
    np.testing.assert_array_equal(found @ hist, sparse.csr_matrix(defined.astype(np.float64)) @ hist)


def test_confidence_recorded_and_an_empty_box_refused_naming_both_candidates(tmp_path: Path) -> None:
    room = scenes.furnished_room()
    room.update_faces(room.face_normals[:, 2] > -0.9)  # no ceiling, as in most reconstructions
    rec = estimate_up(room, ".ply").record()
    assert rec["method"] == "floor" and rec["confidence"] == "high" and not rec["ambiguous"]
    assert rec["floor_area_m2"] == pytest.approx(6 * 4 + 1.2 * 0.8, rel=1e-6)  # the floor and the table top
    # one plane: its mirror image (a ceiling seen from below) is the nearest rival; the file's +Z rules it out
    assert rec["runner_up_angle_deg"] == 180.0 and rec["margin"] > 1.0 and rec["probability"] > 0.9
    assert [c["up"] for c in rec["candidates"]][0] == [0.0, 0.0, 1.0]
    # with its ceiling, only the table (its top scanned, its underside not) tells floor from ceiling
    closed = estimate_up(scenes.furnished_room(), ".ply")
    assert closed.method == "floor" and closed.up.tolist() == [0.0, 0.0, 1.0] and closed.decision is not None
    ceiling = next(c for c in closed.decision.ranked if c.up[2] < -0.99)
    assert closed.record()["evidence"]["furniture"] > 1.0 and ceiling.terms["furniture"] < -1.0
    # an empty closed box: nothing tells floor from ceiling, the file convention picks (flagged low)
    box = scenes.box_room(size=(6.0, 4.0, 2.7))
    src = tmp_path / "box.ply"
    box.export(src)
    space = load_space(src)
    assert space.up_method == "convention-tie"
    assert space.frame_record()["up"]["confidence"] == "low"
    assert any("low confidence (floor and ceiling look alike" in w for w in space.warnings)


def test_a_wall_as_large_as_the_floor_is_refused_naming_both_candidates(tmp_path: Path) -> None:
    """An L-shaped partial scan (floor and one wall of the same size, no ceiling): refused, or taken with a
    guess."""
    floor = trimesh.Trimesh([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], [[0, 1, 2], [0, 2, 3]])
    wall = trimesh.Trimesh([[0, 0, 0], [0, 3, 0], [0, 3, 4], [0, 0, 4]], [[0, 1, 2], [0, 2, 3]])
    scan = trimesh.util.concatenate([floor, wall])
    assert scan.face_normals[:2, 2].min() > 0.99 and scan.face_normals[2:, 0].min() > 0.99
    src = tmp_path / "corner.ply"
    scan.export(src)
    with pytest.raises(UpAmbiguous) as err:
        load_space(src)
    line = str(err.value)
    assert "\n" not in line and line.startswith("corner.ply: up is ambiguous: up ")
    named = {tuple(round(x) for x in c["up"]) for c in err.value.candidates[:2]}
    assert named == {(0, 0, 1), (1, 0, 0)}
    assert "--up=X,Y,Z" in line and "storey " in line and "floor 12 m2" in line
    space = load_space(src, accept_up_guess=True)
    rec = space.frame_record()["up"]
    assert rec["ambiguous"] and rec["confidence"] == "low" and 0.5 <= rec["probability"] < 0.95
    # the capture's camera up settles it
    space = load_space(src, capture_up=[0.2, 0.1, 1.0])
    assert space.up_source.tolist() == [0.0, 0.0, 1.0] and not space.frame_record()["up"]["ambiguous"]


@pytest.mark.parametrize(
    ("storey", "extent", "scale", "unit"),
    [(2.5, 6.0, 1.0, "metres"), (270.0, 800.0, 0.01, "centimetres"), (2600.0, 7000.0, 0.001, "millimetres"),
     (100.0, 300.0, 0.0254, "inches"), (None, 0.15, 1.0, "metres")],
)
def test_units_from_storey_height(storey: float | None, extent: float, scale: float, unit: str) -> None:
    got = choose_unit_scale(storey, extent)
    assert (got.scale, got.unit) == (scale, unit)
    assert got.reason


def test_implausible_object_refused_naming_unit_scale(tmp_path: Path) -> None:
    with pytest.raises(UnitError, match="unit_scale"):
        choose_unit_scale(None, 120.0)
    bunny = trimesh.creation.icosphere(subdivisions=2)
    bunny.apply_scale(400.0)  # an 800 m "ball": an object in the wrong units
    src = tmp_path / "ball.ply"
    bunny.export(src)
    with pytest.raises(SpaceError, match="set unit_scale"):
        load_space(src)
    assert load_space(src, unit_scale=0.001).units.unit == "given"  # an explicit unit_scale always wins


def test_a_room_in_millimetres_far_from_every_axis_loads_levelled(tmp_path: Path) -> None:
    """The issue's case: a furnished room stored in its first camera's frame (up ~37-55 degrees from every
    axis), exported in millimetres."""
    up_src = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)  # 54.7 degrees from each axis
    R = trimesh.geometry.align_vectors([0, 0, 1], up_src)
    room = scenes.furnished_room().apply_transform(R).apply_scale(1000.0)
    src = tmp_path / "scan.ply"
    room.export(src)
    space = load_space(src)
    assert space.up_method == "floor" and space.units.unit == "millimetres"
    np.testing.assert_allclose(space.up_source, up_src, atol=1e-6)
    mesh = space.mesh  # metres again, level
    assert mesh.extents[2] == pytest.approx(2.7, abs=1e-4)
    assert mesh.area == pytest.approx(scenes.furnished_room().area, rel=1e-6)
    floor = mesh.face_normals[:, 2] > 1 - 1e-9
    assert mesh.area_faces[floor].sum() == pytest.approx(6 * 4 + 1.2 * 0.8, rel=1e-6)


def test_given_up_vector_and_source_to_world(tmp_path: Path) -> None:
    src = tmp_path / "room.ply"
    scenes.furnished_room().apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])).export(src)
    given = load_space(src, up=[0.0, -2.0, 0.0])  # any length; +Z went to -Y
    assert given.up_method == "given" and given.units.unit == "metres"  # storey height from the given up
    np.testing.assert_allclose(given.source_to_world[:3, :3] @ [0, -1, 0], [0, 0, 1], atol=1e-12)
    T = np.eye(4)
    T[:3, :3] = 2.0 * trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])[:3, :3]
    T[:3, 3] = [1.0, 2.0, 3.0]
    space = load_space(src, source_to_world=T.tolist())
    assert space.up_method == "source_to_world" and space.units.scale == pytest.approx(2.0)
    np.testing.assert_allclose(space.source_to_world, T)
    ref = trimesh.load(src, force="mesh")
    np.testing.assert_allclose(space.mesh.vertices, trimesh.transform_points(ref.vertices, T), atol=1e-9)
    for bad, msg in [
        (np.diag([1.0, 2.0, 1.0, 1.0]), "uniform scale"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "mirrors"),
        (np.diag([1.0, 1.0, 0.0, 1.0]), "degenerate"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
    ]:
        with pytest.raises(SpaceError, match=msg):
            load_space(src, source_to_world=bad.tolist())


@pytest.mark.parametrize("normal", [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.3, -0.5, 0.81]])
def test_a_flat_scan_is_seen_from_the_side_its_faces_face(normal: list[float]) -> None:
    """A scan of a floor alone (no height at all) is a floor: up is its normal, not the opposite (an OBJ's
    up axis is Y, so on Z the sign is the geometry's)."""
    grid = trimesh.creation.box((3.0, 2.0, 1.0))
    flat = trimesh.Trimesh(*trimesh.remesh.subdivide(grid.vertices,
                                                     grid.faces[grid.face_normals[:, 2] > 0.9]))
    flat.vertices[:, 2] = 0.0
    n = np.asarray(normal) / np.linalg.norm(normal)
    R = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], n)
    est = estimate_up(flat.apply_transform(R), ".obj")
    assert est.method == "floor"
    assert corpus.up_error_deg(est.up, n) < 1e-6


def _tops(*heights_areas: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    h, a = zip(*heights_areas, strict=True)
    return np.asarray(h, dtype=float), np.asarray(a, dtype=float)


def test_unit_evidence_picks_centimetres_or_refuses_never_guesses() -> None:
    from services.core.ingest.frame.unit_evidence import ScanMeasures, decide_units

    # 150 units tall, no ceiling: 1.5 m in cm or 3.81 m in inches; tables at 75 units (0.75 m or 1.9 m)
    partial = ScanMeasures(storey=150.0, extent=(340.0, 250.0, 150.0), ceiling_seen=False,
                           origin_height=145.0, tops=_tops((75.0, 1.0), (45.0, 0.5)), median_edge=4.0)
    d = decide_units(partial)
    assert [c.unit for c in d.ranked] == ["centimetres", "inches"] and not d.ambiguous
    assert d.ranked[0].terms["furniture"] > 0 and d.ranked[1].terms["furniture"] < 0
    # nothing but the height: no camera at the origin, no furniture, coarse triangles
    bare = ScanMeasures(150.0, (340.0, 250.0, 150.0), False, None, None, 100.0)
    assert decide_units(bare).ambiguous
    # a ceiling seen: 1.5 m is no storey, inches (3.81 m) is the only candidate
    closed = decide_units(ScanMeasures(150.0, (340.0, 250.0, 150.0), True, None, None, 100.0))
    assert [c.unit for c in closed.ranked] == ["inches"] and not closed.ambiguous
    assert [c.unit for c in decide_units(
        ScanMeasures(2.5, (5.0, 4.0, 2.5), True, 1.2, _tops((0.7, 1.0)), 0.03)).ranked] == ["metres"]


def test_a_short_partial_room_in_millimetres_is_accepted_an_ambiguous_one_refused() -> None:
    """A floor around sofas and a coffee table, 1.1 m tall (no walls or ceiling above): in millimetres it is
    the only room (1.1 m; 11 m in cm fits nothing); 110 units is 1.1 m in cm or a 2.8 m storey in inches,
    told apart by the seats at 42 units (0.42 m against 1.07 m). Without furniture, asked."""
    from services.core.ingest.frame.unit_evidence import ScanMeasures, decide_units

    seats = _tops((420.0, 1.0), (450.0, 0.3))
    mm = decide_units(ScanMeasures(1100.0, (4700.0, 4000.0, 1100.0), False, None, seats, 23.0))
    assert [c.unit for c in mm.ranked] == ["millimetres"] and not mm.ambiguous
    cm = decide_units(ScanMeasures(110.0, (470.0, 400.0, 110.0), False, None, _tops((42.0, 1.0)), 2.3))
    assert [c.unit for c in cm.ranked] == ["centimetres", "inches"] and not cm.ambiguous
    bare = decide_units(ScanMeasures(110.0, (470.0, 400.0, 110.0), False, None, None, 2.3))
    assert {c.unit for c in bare.ranked} == {"centimetres", "inches"} and bare.ambiguous
    # lower than a room (0.5 m in metres; 5 mm in cm): no unit, whatever the furniture
    assert not decide_units(ScanMeasures(0.5, (4.7, 4.0, 0.5), False, None, _tops((0.42, 1.0)), 0.023)).ranked


def test_a_first_camera_in_a_persons_hands_tells_centimetres_from_inches_and_a_robots_asks() -> None:
    """Single frames in their camera's frame, no furniture to tell: a Kinect frame 1.92 m tall in centimetres
    (bench/scans/rooms/pcl_pairwise_capture0001_kinect), its camera 0.88 m up, is 4.88 m in inches with the
    camera 2.24 m up: read in cm. A robot's frame 1.5 m tall in cm, its camera 0.47 m up, is 3.8 m in inches
    with the camera 1.19 m up, where a person holds one: asked, never read in inches."""
    from services.core.ingest.frame.unit_evidence import ScanMeasures, decide_units

    hands = decide_units(ScanMeasures(192.0, (311.0, 132.0, 192.0), False, 88.0, None, 1.0))
    assert [c.unit for c in hands.ranked] == ["centimetres", "inches"] and not hands.ambiguous
    robot = decide_units(ScanMeasures(150.0, (400.0, 300.0, 150.0), False, 47.0, None, 1.0))
    assert {c.unit for c in robot.ranked} == {"centimetres", "inches"} and robot.ambiguous


def test_unit_evidence_measures_the_tops_of_a_short_partial_room_in_millimetres() -> None:
    """`measure` on a mesh: a 5 x 4 m floor, a 2 x 1 m seat at 450 mm and a wall 1.1 m tall, in mm: the seat
    puts millimetres alone among the units (11 m in cm, 28 m in inches)."""
    from services.core.ingest.frame.unit_evidence import choose_units

    floor = trimesh.creation.box([5000.0, 4000.0, 10.0])
    seat = trimesh.creation.box([2000.0, 1000.0, 10.0]).apply_translation([0.0, 0.0, 450.0])
    wall = trimesh.creation.box([10.0, 4000.0, 1100.0]).apply_translation([2500.0, 0.0, 550.0])
    room = trimesh.util.concatenate([floor, seat, wall])  # tops face up: the floor's and the seat's
    units = choose_units(room, np.array([0.0, 0.0, 1.0]), 1105.0)
    assert units.scale == 0.001 and units.unit == "millimetres" and not units.ambiguous


def test_a_ceiling_over_no_floor_is_a_ceiling_seen() -> None:
    """A ceiling-only capture along its true up: 125 units is a 3.2 m storey in inches, not 1.25 m in cm."""
    from services.core.ingest.frame.unit_evidence import choose_units

    ceiling = trimesh.creation.box([300.0, 200.0, 1.0]).apply_translation([0.0, 0.0, 125.0])
    wall = trimesh.creation.box([1.0, 200.0, 125.0]).apply_translation([150.0, 0.0, 62.5])
    lid = trimesh.util.concatenate([ceiling, wall])
    lid.update_faces(lid.face_normals[:, 2] < 0.5)  # seen from below: no face looks up
    units = choose_units(lid, np.array([0.0, 0.0, 1.0]), 125.5)
    assert units.unit == "inches" and not units.ambiguous


def test_the_median_edge_length_is_trimeshs_median_of_its_unique_edges(scenes_dir: Path) -> None:
    from services.core.ingest.frame.unit_evidence import median_edge_length

    rng = np.random.default_rng(3)
    faces = rng.integers(0, 200, (400, 3))
    faces[:40] = faces[40:80]  # duplicate faces: their edges count once
    faces[80:90, 1] = faces[80:90, 0]  # degenerate faces: an edge from a vertex to itself is an edge too
    soup = trimesh.Trimesh(rng.normal(size=(200, 3)), faces, process=False)
    kitchen = load_space(scenes_dir / "7scenes_redkitchen" / "mesh_tsdf_2cm_from_1000frames.ply").mesh
    for mesh in (soup, kitchen, trimesh.creation.box()):
        assert median_edge_length(mesh) == float(np.median(mesh.copy().edges_unique_length))


def test_counters_that_read_as_seats_2_54_times_off_do_not_decide_the_units() -> None:
    """A room in inches (97 units: a 2.47 m storey, no ceiling) whose tops are counters and cupboards at
    0.9-1.6 m: read in centimetres they are all at 0.36-0.63 m, seat height, but read in inches almost half of
    them are at counter height too. Neither reading separates from the other, so it is asked, never read as a
    0.97 m room in centimetres."""
    from services.core.ingest.frame.unit_evidence import ScanMeasures, decide_units

    tops = _tops((36.0, 0.45), (55.0, 0.3), (63.0, 0.25))  # 0.91, 1.40, 1.60 m in inches
    d = decide_units(ScanMeasures(97.0, (266.0, 198.0, 97.0), False, None, tops, 30.0))
    assert {c.unit for c in d.ranked} == {"centimetres", "inches"} and d.ambiguous
    assert all(c.terms["furniture"] <= 0 for c in d.ranked)
