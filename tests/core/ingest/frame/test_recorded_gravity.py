"""Gravity recorded beside a scan (7-Scenes' gravity-direction.txt): read, weighed as the strongest evidence,
and named in the reason."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from services.core.ingest.errors import UpAmbiguous
from services.core.ingest.frame.recorded_gravity import read_recorded_up
from services.core.ingest.loading import load_space

REPO = Path(__file__).resolve().parents[4]


def _write_gravity(folder: Path, down: list[float] | str) -> None:
    text = down if isinstance(down, str) else "\n".join(f"{x:.9e}" for x in down)
    (folder / "gravity-direction.txt").write_text(text + "\n")


def test_the_recorded_down_is_read_as_up_and_a_bad_file_is_ignored(tmp_path: Path) -> None:
    assert read_recorded_up(tmp_path) is None
    _write_gravity(tmp_path, [0.0, 2.0, 0.0])
    rec = read_recorded_up(tmp_path)
    assert rec is not None and rec.up.tolist() == [0.0, -1.0, 0.0] and rec.source == "gravity-direction.txt"
    for bad in ("0 0 0", "1 2", "up is +y", "1 2 nan"):
        _write_gravity(tmp_path, bad)
        assert read_recorded_up(tmp_path) is None, bad


def test_a_floor_as_large_as_a_wall_is_levelled_on_the_recorded_gravity(tmp_path: Path) -> None:
    """A corner (floor and wall of one size) is ambiguous on its geometry; with the gravity its capture
    recorded beside it, it levels exactly on that gravity and the reason says so."""
    floor = trimesh.Trimesh([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], [[0, 1, 2], [0, 2, 3]])
    wall = trimesh.Trimesh([[0, 0, 0], [0, 3, 0], [0, 3, 4], [0, 0, 4]], [[0, 1, 2], [0, 2, 3]])
    trimesh.util.concatenate([floor, wall]).export(tmp_path / "corner.ply")
    down = np.array([0.01, -0.02, -1.0])
    _write_gravity(tmp_path, down.tolist())
    space = load_space(tmp_path / "corner.ply")
    np.testing.assert_allclose(space.up_source, -down / np.linalg.norm(down))
    up = space.frame_record()["up"]
    assert up["confidence"] == "high" and up["reason"].startswith("the gravity recorded with the scan")
    assert up["evidence"]["recorded_gravity"] > 0
    assert min(c["evidence"]["recorded_gravity"] for c in up["candidates"]) < 0


def test_a_real_partial_room_levels_on_its_recorded_gravity_whatever_its_floor_says(tmp_path: Path) -> None:
    """A real 7-Scenes window (its truth is the capture's gravity): up is the recorded gravity to the bit, not
    the scanned floor's mean normal."""
    truth = json.loads((REPO / "tests" / "fixtures" / "real_scans" / "truth.json").read_text())
    name = "kitchen_partial_340.ply"
    shutil.copy(REPO / "tests" / "fixtures" / "real_scans" / name, tmp_path / name)
    up = np.asarray(truth[name]["up"], dtype=float)
    _write_gravity(tmp_path, (-up).tolist())
    space = load_space(tmp_path / name)
    np.testing.assert_allclose(space.up_source, up / np.linalg.norm(up), atol=1e-8)
    assert "the gravity recorded with the scan" in space.frame_record()["up"]["reason"]


def test_an_aria_trajectory_beside_the_points_gives_its_gravity_and_travels_with_the_scan(
        tmp_path: Path) -> None:
    """Project Aria MPS writes gravity per trajectory row (gravity_*_world, m/s^2): read as up, and packed
    with the mesh when it is stored, so the stored space levels the same."""
    from services.core.ingest.registry import pack_source

    header = "graph_uid,tx_world_device,gravity_x_world,gravity_y_world,gravity_z_world,quality_score"
    rows = [f"g,0.1,{x:.4f},0.0000,-9.8100,0.5" for x in (0.01, -0.01)]
    (tmp_path / "closed_loop_trajectory.csv").write_text("\n".join([header, *rows]) + "\n")
    rec = read_recorded_up(tmp_path)
    assert rec is not None and rec.source == "closed_loop_trajectory.csv"
    np.testing.assert_allclose(rec.up, [0.0, 0.0, 1.0])
    floor = trimesh.Trimesh([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], [[0, 1, 2], [0, 2, 3]])
    wall = trimesh.Trimesh([[0, 0, 0], [0, 3, 0], [0, 3, 4], [0, 0, 4]], [[0, 1, 2], [0, 2, 3]])
    trimesh.util.concatenate([floor, wall]).export(tmp_path / "corner.ply")
    work = tmp_path / "work"
    work.mkdir()
    packed = pack_source(tmp_path / "corner.ply", tmp_path / "corner.ply", work)
    with zipfile.ZipFile(packed) as zf:
        assert sorted(zf.namelist()) == ["closed_loop_trajectory.csv", "corner.ply"]
    assert load_space(packed).up_source.tolist() == [0.0, 0.0, 1.0]
    (tmp_path / "closed_loop_trajectory.csv").write_text("graph_uid,tx_world_device\ng,0.1\n")
    assert read_recorded_up(tmp_path) is None  # no gravity columns: not this format


def test_a_recorded_gravity_the_geometry_clearly_contradicts_is_refused_not_followed(tmp_path: Path) -> None:
    """A stale gravity file (down along a wall of a real room whose floor the geometry finds clearly): the two
    disagree, so loading asks, the recorded up first and the floor next, rather than level on either."""
    name = "kitchen_full.ply"
    truth = json.loads((REPO / "tests" / "fixtures" / "real_scans" / "truth.json").read_text())
    shutil.copy(REPO / "tests" / "fixtures" / "real_scans" / name, tmp_path / name)
    up = np.asarray(truth[name]["up"], dtype=float)
    up /= np.linalg.norm(up)
    wall = np.cross(up, [1.0, 0.0, 0.0])
    _write_gravity(tmp_path, (-wall / np.linalg.norm(wall)).tolist())
    with pytest.raises(UpAmbiguous) as err:
        load_space(tmp_path / name)
    assert "the gravity recorded beside it and its geometry disagree" in str(err.value)
    floor = np.asarray(err.value.candidates[1]["up"], dtype=float)
    assert float(floor @ up) > np.cos(np.radians(5.0))
    assert load_space(tmp_path / name, accept_up_guess=True).frame_record()["up"]["ambiguous"]
    # a gravity no plane of the scan agrees with (45 degrees off the floor): refused the same way
    tilted = up + wall / np.linalg.norm(wall)
    _write_gravity(tmp_path, (-tilted / np.linalg.norm(tilted)).tolist())
    with pytest.raises(UpAmbiguous, match="the gravity recorded beside it and its geometry disagree"):
        load_space(tmp_path / name)
