"""`omnidata plan`/`generate` on a real room whose walls are as large as its floor (the BundleFusion copy
room), rotated and in millimetres: stop with one line naming the candidates and --up; plan with the --up the
user picks, or on the guess when --accept-up-guess is given; job.json reports the probability and the
evidence."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from tests.fixtures.cli import omnidata
from tests.fixtures.real_corpus import REAL_SCANS, real_rooms, units_ambiguous_scan
from tests.fixtures.rotation_corpus import up_error_deg


def _rotated_mm(tmp_path: Path) -> tuple[Path, np.ndarray]:
    room = next(r for r, _ in real_rooms() if r.name == "copyroom")
    R = Rotation.from_euler("xyz", [63, -21, 140], degrees=True).as_matrix()
    mesh = trimesh.load(REAL_SCANS / "copyroom.ply", process=False)
    mesh.vertices = (mesh.vertices @ R.T) * 1000.0
    src = tmp_path / "partial_rot_mm.ply"
    mesh.export(src)
    return src, R @ room.up


def _level_error(job_json: Path, truth: np.ndarray) -> tuple[float, dict]:
    space = next(iter(json.loads(job_json.read_text())["spaces"].values()))
    world = np.array(space["source_to_world"])[:3, :3] @ truth
    return up_error_deg(world, np.array([0.0, 0.0, 1.0])), space


def test_plan_stops_then_plans_with_the_picked_up(tmp_path: Path) -> None:
    src, truth = _rotated_mm(tmp_path)
    args = ["--points", 2, "--min-views", 1, "--seed", 1]
    res = omnidata("plan", src, "--out", tmp_path / "p", *args)
    assert res.returncode == 2, res.stdout + res.stderr
    line = res.stderr.strip()
    assert "\n" not in line and "partial_rot_mm.ply: up is ambiguous: up " in line and "--up=X,Y,Z" in line
    assert line.count("storey ") >= 2 and line.count("floor ") >= 2
    assert not (tmp_path / "p" / "job.json").exists()
    # the candidates in the line are source vectors: one of them is the measured up
    named = [
        np.array(m.split(","), dtype=float)
        for m in re.findall(r"up ([-\d.e+]+,[-\d.e+]+,[-\d.e+]+) \(floor", line)
    ]
    assert len(named) >= 2
    right = min(named, key=lambda v: up_error_deg(v, truth))
    assert up_error_deg(right, truth) < 3.0

    res = omnidata("plan", src, "--out", tmp_path / "q", "--up=" + ",".join(f"{x:.6g}" for x in right), *args)
    assert res.returncode == 0, res.stderr
    err, space = _level_error(tmp_path / "q" / "job.json", truth)
    assert err < 3.0 and space["units"]["unit_scale"] == 0.001 and space["up"]["method"] == "given"

    res = omnidata("plan", src, "--out", tmp_path / "r", "--accept-up-guess", *args)
    assert res.returncode == 0, res.stderr
    _, space = _level_error(tmp_path / "r" / "job.json", truth)
    up = space["up"]
    assert up["ambiguous"] and up["confidence"] == "low" and 0.5 <= up["probability"] < 1.0
    assert {"floor_area", "extent", "storey", "levelled_axis", "format_up"} <= set(up["evidence"])
    assert len(up["candidates"]) >= 2 and "low confidence" in res.stderr


def test_generate_stops_before_rendering(tmp_path: Path) -> None:
    src, _ = _rotated_mm(tmp_path)
    res = omnidata("generate", src, "--out", tmp_path / "g", "--workers", 1, "--no-progress", timeout=120)
    assert res.returncode == 2, res.stdout + res.stderr
    assert (
        "up is ambiguous" in res.stderr and "--up=X,Y,Z" in res.stderr and "--accept-up-guess" in res.stderr
    )


def test_plan_stops_on_ambiguous_units_then_plans_with_unit_scale(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A real room 2.1 m tall in inches, too little in it telling the units (`units_ambiguous_scan`): 2.1 m in
    inches or 0.83 m in centimetres; the line names both, inches first (its first camera 1.51 m up, where a
    person holds one, against 0.59 m in cm, where a robot's could be)."""
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(tmp_path / "data"))  # the meshed cloud is cached there
    src = units_ambiguous_scan(tmp_path / "partial_in.ply")
    room_up = np.array([0.0, 0.0, 1.0])
    up = "--up=0,0,1"
    args = ["--points", 2, "--min-views", 1, "--seed", 1]
    res = omnidata("plan", src, "--out", tmp_path / "p", up, *args)
    assert res.returncode == 2, res.stdout + res.stderr
    line = res.stderr.strip()
    assert (
        "\n" not in line
        and "partial_in.ply: units are ambiguous: inches (--unit-scale=0.0254: storey" in line
    )
    assert "centimetres (--unit-scale=0.01: storey" in line and not (tmp_path / "p" / "job.json").exists()
    res = omnidata("plan", src, "--out", tmp_path / "q", up, "--unit-scale", "0.0254", *args)
    assert res.returncode == 0, res.stderr
    _, space = _level_error(tmp_path / "q" / "job.json", room_up)
    assert space["units"]["unit_scale"] == 0.0254 and space["units"]["unit"] == "given"
