"""`omnidata plan`: files in the dataset layout, job.json, and clear refusals (exit 2)."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from services.cli import main
from services.core.domain.keys import file_name
from services.core.domain.plan import plan_from_json
from services.core.domain.plan_cues import nonfixated, point_info, vanishing_points
from services.core.ingest.loading import load_space
from tests.fixtures import scenes

SPEC = {
    "name": "demo",
    "cameras": {"max_count": 12, "min_spacing_m": 1.0},
    "points": {"min_views": 3, "max_views": 3},
}


@pytest.fixture
def room(tmp_path: Path) -> Path:
    path = tmp_path / "in" / "my room.ply"
    path.parent.mkdir()
    scenes.pillar_room().export(path)
    return path


@pytest.fixture
def spec_file(tmp_path: Path) -> Path:
    path = tmp_path / "job.yaml"
    path.write_text(yaml.safe_dump(SPEC))
    return path


def test_plan_writes_the_dataset_layout(tmp_path: Path, room: Path, spec_file: Path, capsys) -> None:
    out = tmp_path / "out"
    rc = main(["plan", str(room), "--out", str(out), "--spec", str(spec_file), "--points", "6", "--seed", "3",
               "--resolution", "128"])
    assert rc == 0, capsys.readouterr().err
    job = json.loads((out / "job.json").read_text())
    assert job["spec"]["points"]["count"] == 6 and job["spec"]["seed"] == 3
    assert job["spec"]["views"]["resolution"] == 128 and job["component"] == "demo"
    assert set(job["conventions"]) >= {"world", "camera_axes", "K", "fragments"}
    assert job["code_version"]
    rec = job["spaces"]["my_room"]  # the file stem, sanitised
    assert rec["counts"] == {"cameras": 12, "points": 6, "views": 18} and rec["shortfall"] is None
    space = load_space(room)
    np.testing.assert_allclose(rec["source_to_world"], space.source_to_world)
    assert rec["checksum_sha256"] == space.checksum

    plan = plan_from_json((out / rec["plan"]).read_text())
    base = "demo/my_room"
    for view in plan.views:
        info_path = out / "point_info" / base / file_name("point_info", view.point_idx, view.v)
        info = json.loads(info_path.read_text())
        assert info == json.loads(json.dumps(point_info(plan, view)))
        vp = json.loads(
            (
                out / "vanishing_points" / base / file_name("vanishing_points", view.point_idx, view.v)
            ).read_text()
        )
        assert vp == json.loads(json.dumps(vanishing_points(info)))
    for p in plan.points:
        doc = json.loads((out / "nonfixated" / base / f"point_{p.idx}_domain_nonfixated.json").read_text())
        assert doc == json.loads(json.dumps(nonfixated(plan, p.idx)))
    assert len(list((out / "point_info" / base).iterdir())) == 18
    assert len(list((out / "vanishing_points" / base).iterdir())) == 18
    assert len(list((out / "nonfixated" / base).iterdir())) == 6
    assert "my_room: 12 cameras, 6 points, 18 views" in capsys.readouterr().out

    again = tmp_path / "again"
    assert (
        main(
            [
                "plan", str(room), "--out", str(again), "--spec", str(spec_file), "--points", "6", "--seed",
                "3", "--resolution", "128",
            ]
        )
        == 0
    )
    assert (again / rec["plan"]).read_bytes() == (out / rec["plan"]).read_bytes()  # same seed, same bytes


def test_plan_from_a_zip_and_a_shortfall_warning(tmp_path: Path, room: Path, capsys) -> None:
    z = tmp_path / "scan.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.write(room, "scan/room.ply")
    spec = tmp_path / "job.json"
    spec.write_text(json.dumps({"cameras": {"mode": "provided", "poses": [
        {"location": [1, 1, 1.2]}, {"location": [2, 3, 1.2]}, {"location": [5, 1, 1.2]}]},
        "points": {"count": 50, "max_tries_per_point": 1, "min_views": 3}}))
    rc = main(["plan", str(z), "--out", str(tmp_path / "o"), "--spec", str(spec)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    rec = json.loads((tmp_path / "o" / "job.json").read_text())["spaces"]["scan"]
    assert rec["counts"]["points"] < 50 and rec["shortfall"].startswith("space yields")
    assert "warning: scan: space yields" in captured.err


@pytest.mark.parametrize(
    ("spec", "extra", "message"),
    [
        ({"points": {"min_views": 0}}, [], "points.min_views: Input should be greater than or equal to 1"),
        (
            {}, ["--min-views", "0"],
            "points.min_views (--min-views): Input should be greater than or equal to 1",
        ),
        ({"cameras": {"colour": 1}}, [], "cameras.colour: Extra inputs are not permitted"),
        ({"views": {"resolution": 8}}, [], "views.resolution: Input should be greater than or equal to 16"),
        ({"cues": ["segment_semantic"]}, [], "needs semantic labels"),
        ({"cameras": {"max_count": 2}}, [], "has 2 cameras"),
        ({}, ["--name", "../up"], "name (--name): name '../up' is not a valid name"),
    ],
)
def test_bad_specs_are_refused_naming_the_field(
    tmp_path: Path, room: Path, capsys, spec, extra, message
) -> None:
    path = tmp_path / "job.yaml"
    path.write_text(yaml.safe_dump(spec))
    rc = main(["plan", str(room), "--out", str(tmp_path / "o"), "--spec", str(path), *extra])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("omnidata plan: error: ")
    assert message in err
    assert not (tmp_path / "o" / "job.json").exists()


def test_bad_inputs_are_refused_clearly(tmp_path: Path, room: Path, capsys) -> None:
    def refuse(args: list[str], message: str) -> None:
        rc = main(["plan", *args, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert rc == 2 and message in err, err

    refuse([str(tmp_path / "nope.ply")], "nope.ply: no such file or folder")
    (tmp_path / "bad.yaml").write_text("points: [1, 2\n")
    refuse([str(room), "--spec", str(tmp_path / "bad.yaml")], "not valid YAML")
    refuse([str(room), "--spec", str(tmp_path / "missing.yaml")], "missing.yaml: no such file")
    (tmp_path / "list.yaml").write_text("- 1\n")
    refuse([str(room), "--spec", str(tmp_path / "list.yaml")], "expected a mapping of JobSpec fields")
    twin = tmp_path / "other" / "my room.ply"
    twin.parent.mkdir()
    twin.write_bytes(room.read_bytes())
    refuse([str(room), str(twin)], "two spaces would share the name 'my_room'")
    (tmp_path / "evil.zip").write_bytes(b"PK\x03\x04 not really")
    refuse([str(tmp_path / "evil.zip")], "not a readable zip archive")
    refuse([str(room), "--unit-scale", "0.0001"], "check unit_scale")
    assert not (tmp_path / "o").exists()
    with pytest.raises(SystemExit) as e:
        main(["plan", str(room), "--out", str(tmp_path / "o"), "--up-axis", "sideways"])
    assert e.value.code == 2
    assert "invalid choice: 'sideways'" in capsys.readouterr().err


def test_plan_prints_and_records_the_detected_frame(tmp_path: Path, capsys) -> None:
    """A room in millimetres, tilted off every axis: plan says what it found; --up and --source-to-world
    override."""
    R = trimesh.geometry.align_vectors([0, 0, 1], [1.0, 2.0, 2.0])
    src = tmp_path / "scan.ply"
    scenes.furnished_room().apply_transform(R).apply_scale(1000.0).export(src)
    out = tmp_path / "out"
    assert main(["plan", str(src), "--out", str(out), "--points", "3", "--resolution", "32"]) == 0
    printed = capsys.readouterr().out
    assert "scan: up [0.3333, 0.6667, 0.6667] (floor," in printed and "units: millimetres x0.001" in printed
    rec = json.loads((out / "job.json").read_text())["spaces"]["scan"]
    assert rec["up"]["method"] == "floor" and rec["up"]["confidence"] in ("high", "low")
    np.testing.assert_allclose(rec["up"]["source_direction"], [1 / 3, 2 / 3, 2 / 3], atol=1e-6)
    assert rec["units"] == {"unit_scale": 0.001, "unit": "millimetres", "reason": rec["units"]["reason"]}
    assert (
        rec["valid_fraction"]["views"] == rec["counts"]["views"] and 0 < rec["valid_fraction"]["median"] <= 1
    )

    T = np.eye(4)
    T[:3, :3] = 0.001 * R[:3, :3].T
    matrix = tmp_path / "s2w.json"
    matrix.write_text(json.dumps(T.tolist()))
    assert main(["plan", str(src), "--out", str(tmp_path / "o2"), "--points", "3", "--resolution", "32",
                 "--source-to-world", str(matrix)]) == 0
    rec = json.loads((tmp_path / "o2" / "job.json").read_text())["spaces"]["scan"]
    np.testing.assert_allclose(rec["source_to_world"], T)
    assert rec["up"]["method"] == "source_to_world"
    assert main(["plan", str(src), "--out", str(tmp_path / "o3"), "--points", "3", "--resolution", "32",
                 "--up", "1,2,2", "--unit-scale", "0.001"]) == 0
    rec = json.loads((tmp_path / "o3" / "job.json").read_text())["spaces"]["scan"]
    assert rec["up"]["method"] == "given" and rec["units"]["unit"] == "given"


def test_frame_flags_refused_clearly(tmp_path: Path, room: Path, capsys) -> None:
    shear = tmp_path / "shear.txt"
    shear.write_text("1 0.5 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    rc = main(["plan", str(room), "--out", str(tmp_path / "o"), "--source-to-world", str(shear)])
    err = capsys.readouterr().err
    assert rc == 2 and "source_to_world" in err and "rotation times a uniform scale" in err, err
    assert len(err.strip().splitlines()) == 1
    rc = main(["plan", str(room), "--out", str(tmp_path / "o"), "--up", "0,0,1", "--up-axis=+y"])
    assert rc == 2 and "either up" in capsys.readouterr().err
    for flag, value in (("--up", "1,2"), ("--unit-scale", "big")):
        with pytest.raises(SystemExit) as e:
            main(["plan", str(room), "--out", str(tmp_path / "o"), flag, value])
        assert e.value.code == 2
    assert not (tmp_path / "o").exists()


def test_plan_reports_trajectory_clips_in_job_json(tmp_path: Path, capsys) -> None:
    room = tmp_path / "room.ply"
    scenes.random_furnished_room(np.random.default_rng(41)).export(room)
    spec = tmp_path / "video.yaml"
    spec.write_text(
        yaml.safe_dump(
            {
                "points": {"count": 6},
                "views": {
                    "mode": "trajectory", "trajectory_max_frames": 60, "trajectory_min_frames": 30,
                    "resolution": 32,
                },
            }
        )
    )
    out = tmp_path / "out"
    assert main(["plan", str(room), "--out", str(out), "--spec", str(spec), "--seed", "1"]) == 0
    assert "trajectory clips of 6 points" in capsys.readouterr().err
    rec = json.loads((out / "job.json").read_text())["spaces"]["room"]
    plan = plan_from_json((out / rec["plan"]).read_text())
    clips = rec["clips"]
    assert clips["dropped"] == sum(n["outcome"] == "dropped" for n in plan.clip_notes) > 0
    assert clips["shortened"] + clips["dropped"] == len(plan.clip_notes) == len(clips["notes"])
    assert rec["counts"]["points"] == 6 - clips["dropped"] and "trajectory clips" in rec["shortfall"]
