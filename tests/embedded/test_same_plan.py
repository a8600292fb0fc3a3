"""One seeding rule: `omnidata plan` and `omnidata generate` (and so the service, whose scheduler generate
runs) give the same plan for the same space + spec + seed, whatever the order or number of spaces in the
job."""

from __future__ import annotations

from pathlib import Path

from tests.fixtures.cli import omnidata as run_omnidata

SPEC = """
cameras: {mode: object, object_count: 6}
points: {count: 2, min_views: 2, max_views: 2}
views: {resolution: 16}
cues: [point_info]
"""


def omnidata(*args: str | Path) -> None:
    res = run_omnidata(*args)
    assert res.returncode == 0, res.stderr


def point_infos(out: Path, space: str) -> dict[str, bytes]:
    files = sorted((out / "point_info" / "demo" / space).glob("*.json"))
    assert files, f"no point_info files for {space} in {out}"
    return {p.name: p.read_bytes() for p in files}


def test_plan_and_generate_write_the_same_point_info_bytes(tmp_path: Path, scenes_dir: Path) -> None:
    spec = tmp_path / "job.yaml"
    spec.write_text(SPEC)
    bunny, banana = scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply", scenes_dir / "ycb_banana"
    # The bunny alone with plan; second of two spaces with generate (its position in the job differs).
    omnidata("plan", bunny, "--out", tmp_path / "plan", "--spec", spec, "--seed", 3, "--name", "demo")
    omnidata(
        "generate", banana, bunny, "--out", tmp_path / "gen", "--spec", spec, "--seed", 3, "--name", "demo",
        "--workers", 1, "--no-progress",
    )
    assert point_infos(tmp_path / "plan", "bun_zipper_res2") == point_infos(
        tmp_path / "gen", "bun_zipper_res2"
    )
    # and the banana's plan does not depend on the bunny being in the job
    omnidata("plan", banana, "--out", tmp_path / "plan2", "--spec", spec, "--seed", 3, "--name", "demo")
    assert point_infos(tmp_path / "plan2", "ycb_banana") == point_infos(tmp_path / "gen", "ycb_banana")
