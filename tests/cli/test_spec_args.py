"""services/cli/spec_args.py: the one parser of SPACE arguments and JobSpec flags for plan, generate and
submit."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from services.cli import CliError
from services.cli.main import build_parser
from services.cli.spec_args import build_spec, check_sources, distinct_space_names
from services.core.domain.keys import space_name

SPEC_FLAGS = {
    "--spec", "--cues", "--points", "--min-views", "--resolution", "--seed", "--name", "--up-axis", "--up",
    "--unit-scale", "--source-to-world",
}


def options(command: str) -> set[str]:
    parser = build_parser([command])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {s for a in sub.choices[command]._actions for s in a.option_strings}


@pytest.mark.parametrize("command", ["plan", "generate", "submit"])
def test_every_command_takes_the_same_spec_flags(command: str) -> None:
    assert SPEC_FLAGS <= options(command)


def test_space_names_strip_both_ends_and_unsafe_characters(tmp_path: Path) -> None:
    assert space_name(Path("/x/scan_.obj")) == "scan"
    assert space_name(Path("/x/_scan.obj")) == "scan"
    assert space_name(Path("/x/My Scan (2).ply")) == "My_Scan_2"
    assert space_name(Path("/x/___.ply")) == "space"
    (tmp_path / "room.v2").mkdir()
    assert space_name(tmp_path / "room.v2") == "room.v2"  # a folder keeps its whole name
    with pytest.raises(CliError, match="two spaces would share the name 'scan'"):
        distinct_space_names([Path("a/scan.obj"), Path("b/scan_.ply")])


def parse(*argv: str) -> argparse.Namespace:
    return build_parser(["plan"]).parse_args(["plan", "x.obj", "--out", "o", *argv])


def test_flags_override_the_spec_file_and_errors_name_field_and_flag(tmp_path: Path) -> None:
    spec = tmp_path / "job.yaml"
    spec.write_text("seed: 1\npoints:\nviews: {resolution: 64}\ncues: [rgb]\n")
    got = build_spec(parse("--spec", str(spec), "--points", "4", "--cues", "rgb, normal", "--seed", "9"))
    assert (got.seed, got.points.count, got.views.resolution, got.cues) == (9, 4, 64, ["rgb", "normal"])
    with pytest.raises(
        CliError, match=r"points.min_views \(--min-views\): Input should be greater than or equal to 1"
    ):
        build_spec(parse("--min-views", "0"))
    with pytest.raises(
        CliError, match=r"^invalid job spec: name \(--name\): name '\.\./x' is not a valid name"
    ):
        build_spec(parse("--name", "../x"))
    with pytest.raises(CliError, match="missing.yaml: no such file"):
        build_spec(parse("--spec", str(tmp_path / "missing.yaml")))
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(CliError, match="expected a mapping of JobSpec fields, got list"):
        build_spec(parse("--spec", str(tmp_path / "list.yaml")))


def test_sources_are_checked_before_anything_is_loaded(tmp_path: Path, scenes_dir: Path) -> None:
    with pytest.raises(CliError, match="nope.obj: no such file or folder"):
        check_sources([str(tmp_path / "nope.obj")])
    bunny = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
    (src,) = check_sources([str(bunny)])
    assert src.name == "bun_zipper_res2" and len(src.checksum) == 64 and src.path == bunny.resolve()


def test_frame_flags_set_the_frame_fields(tmp_path: Path) -> None:
    got = build_spec(parse("--up", "0,1,0", "--unit-scale", "0.01"))
    assert (got.up, got.unit_scale, got.up_axis) == ((0.0, 1.0, 0.0), 0.01, "auto")
    matrix = tmp_path / "m.txt"
    matrix.write_text("0 0 2 1\n2 0 0 0\n0 2 0 0\n0 0 0 1\n")
    got = build_spec(parse("--source-to-world", str(matrix)))
    assert got.source_to_world is not None and got.source_to_world[0] == (0.0, 0.0, 2.0, 1.0)
    with pytest.raises(CliError, match="source_to_world sets the whole frame: leave up_axis unset"):
        build_spec(parse("--source-to-world", str(matrix), "--up-axis=+y"))


def test_a_dataset_root_is_one_source_per_scene_named_by_its_id(tmp_path: Path) -> None:
    from services.cli.spec_args import refused_summary, usable
    from tests.fixtures import scan_datasets as ds

    scans, split = tmp_path / "ScanNet" / "scans", tmp_path / "hm3d" / "train"
    ds.write_scannet_scene(scans, "scene0000_00")
    ds.write_scannet_scene(scans, "scene0707_00")
    ds.write_hm3d_scene(split, "00801", "HaxA7YrQdEC", plain=False)
    single = ds.write_replica_scene(tmp_path / "replica")  # a scene folder given as itself: one space
    sources = check_sources([str(scans), str(split), str(single)])
    assert [(s.name, s.from_root, s.refused is None) for s in sources] == [
        ("scene0000_00", True, True), ("scene0707_00", True, True), ("00801-HaxA7YrQdEC", True, False),
        ("room_0", False, True)]
    assert all(s.checksum for s in sources if s.refused is None)
    assert "00801-HaxA7YrQdEC: HaxA7YrQdEC.basis.glb" in refused_summary(sources)
    assert [s.name for s in usable(sources)] == ["scene0000_00", "scene0707_00", "room_0"]
    with pytest.raises(CliError, match="every scene was refused"):
        usable(check_sources([str(split)]))
