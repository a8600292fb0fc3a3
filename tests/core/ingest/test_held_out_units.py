"""Units of a held-out short partial room (shared/rooms_held_out: a living room's floor around a coffee table
and two sofas, 1.1 m tall, no walls or ceiling above; TEASER++ sample, MIT): read in the unit that puts its
seats at seat height, and asked for when nothing in it tells the units."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from services.core.ingest.errors import UnitsAmbiguous
from services.core.ingest.loading import load_space

REPO = Path(__file__).resolve().parents[3]
ROOM = REPO / "shared" / "rooms_held_out" / "teaser_uw_rgbd_living_room" / "teaser_uw_rgbd_living_room.ply"
UP = np.array([-0.043295, -0.979856, -0.194957])  # bench/scans/rooms/truth.json


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> trimesh.Trimesh:
    # the meshed cloud cached in the test's own folder, not the user's
    cache = tmp_path_factory.mktemp("meshed")
    return load_space(ROOM, source_to_world=np.eye(4).tolist(), cloud_cache_dir=cache).mesh


def _export(mesh: trimesh.Trimesh, metres_per_unit: float, path: Path) -> Path:
    copy = mesh.copy()
    copy.apply_scale(1.0 / metres_per_unit)
    copy.export(path)
    return path


@pytest.mark.parametrize(("unit", "scale"),
                         [("millimetres", 0.001), ("centimetres", 0.01), ("inches", 0.0254)])
def test_short_partial_room_levelled_in_its_unit(room: trimesh.Trimesh, tmp_path: Path, unit: str,
                                                 scale: float) -> None:
    """1.1 m tall fits no storey; its seats at 0.42 m fit one unit only (in cm, inches would make them 1.07 m
    on a 2.8 m storey)."""
    space = load_space(_export(room, scale, tmp_path / f"room_{unit}.ply"), up=UP / np.linalg.norm(UP))
    assert space.units is not None and space.units.unit == unit and not space.units.ambiguous
    assert space.units.scale == scale


def test_short_partial_room_without_its_furniture_is_asked_for(room: trimesh.Trimesh, tmp_path: Path) -> None:
    """The same floor in centimetres with every surface above the floor that faces up cut away: 1.1 m in cm or
    a 2.8 m storey in inches, nothing tells them apart: refused naming both."""
    up = UP / np.linalg.norm(UP)
    h = room.triangles_center @ up
    h = h - float((room.vertices @ up).min())
    height = float(np.ptp(room.vertices @ up))
    tops = (room.face_normals @ up > 0.9) & (h > 0.1 * height)
    bare = room.copy()
    bare.update_faces(~tops)
    with pytest.raises(UnitsAmbiguous) as err:
        load_space(_export(bare, 0.01, tmp_path / "bare_cm.ply"), up=up)
    assert {c["unit"] for c in err.value.candidates} == {"centimetres", "inches"}
