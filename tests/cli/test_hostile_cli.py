"""Hostile scan files on the command line (issues 11 and 19): `omnidata plan` and `omnidata generate` refuse
each with one line on stderr and exit status 2, before anything is written, and never open a file outside
the scan's folder (the server's secret files are watched with inotify)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli import main
from tests.fixtures.file_watch import OpenWatch
from tests.fixtures.hostile_corpus import HOSTILE_FILES, HOSTILE_FOLDERS, secret_files


def _write(tmp_path: Path, case: str) -> Path:
    filename, make, _needles = HOSTILE_FILES[case]
    path = tmp_path / case / filename
    path.parent.mkdir(parents=True)
    path.write_bytes(make())
    return path


def test_plan_refuses_every_hostile_file_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    failures = []
    for case, (_filename, _make, needles) in sorted(HOSTILE_FILES.items()):
        out = tmp_path / "out" / case
        code = main(["plan", str(_write(tmp_path, case)), "--out", str(out)])
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        ok = (
            code == 2
            and len(lines) == 1
            and lines[0].startswith("omnidata plan: error: ")
            and any(n.lower() in err.lower() for n in needles)
            and not out.exists()
        )
        if not ok:
            failures.append((case, code, err[-300:]))
    assert not failures, failures


@pytest.mark.parametrize(
    "case", ["zip_bad_crc", "zip_corrupt_deflate", "obj_truncated_mid_token", "texture_dotdot_path"]
)
def test_generate_refuses_corrupt_files_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    out = tmp_path / "out"
    code = main(["generate", str(_write(tmp_path, case)), "--out", str(out), "--no-progress"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("omnidata generate: error: "), lines
    assert any(n in lines[0] for n in HOSTILE_FILES[case][2]) and "Traceback" not in lines[0]
    assert not out.exists()


def _refused_in_one_line(code: int, err: str, command: str, needles: tuple[str, ...]) -> bool:
    lines = err.strip().splitlines()
    return (code == 2 and len(lines) == 1 and lines[0].startswith(f"omnidata {command}: error: ")
            and any(n.lower() in err.lower() for n in needles) and "Traceback" not in err)


def test_plan_and_generate_never_open_a_file_outside_the_scan(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    secrets = secret_files()
    files = {case: _write(tmp_path, case) for case in HOSTILE_FILES}
    folders = {}
    for case, (build, _needles) in HOSTILE_FOLDERS.items():
        folders[case] = tmp_path / "folders" / case
        folders[case].mkdir(parents=True)
        build(folders[case])
    failures = []
    with OpenWatch(secrets.values()) as watch:
        for case, path in [*files.items(), *folders.items()]:
            needles = HOSTILE_FILES[case][2] if case in HOSTILE_FILES else HOSTILE_FOLDERS[case][1]
            for command in ("plan", "generate") if case in HOSTILE_FOLDERS else ("plan",):
                out = tmp_path / "out" / command / case
                extra = ["--no-progress"] if command == "generate" else []
                code = main([command, str(path), "--out", str(out), *extra])
                err = capsys.readouterr().err
                if not _refused_in_one_line(code, err, command, needles) or out.exists():
                    failures.append((command, case, code, err[-300:]))
        opened = watch.opened()
    assert not failures, failures
    assert opened == [], f"a hostile scan made the CLI open {opened}"


def test_plan_of_a_capture_whose_photos_are_over_the_budget_names_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], scenes_dir: Path
) -> None:
    import shutil

    from services.core.ingest.capture.photos import MAX_PHOTO_PIXELS
    from tests.fixtures.captures import toy_frames, write_colmap
    from tests.fixtures.hostile_corpus import png_declaring

    folder = tmp_path / "scan"
    folder.mkdir()
    shutil.copy(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply", folder / "bunny.ply")
    frames = toy_frames(2)
    write_colmap(folder, frames)
    cameras = folder / "sparse" / "0" / "cameras.txt"  # the cameras agree with the photos' headers
    cameras.write_text(cameras.read_text().replace(" 64 48 ", " 12000 12000 "))
    for f in frames:
        (folder / "images" / f"{f.name}.jpg").write_bytes(png_declaring(12000, 12000))
    spec = tmp_path / "capture.yaml"
    spec.write_text("cameras: {mode: capture}\nviews: {resolution: 64}\n")
    out = tmp_path / "out"
    code = main(["plan", str(folder), "--out", str(out), "--spec", str(spec)])
    err = capsys.readouterr().err
    limit = f"more than the limit of {MAX_PHOTO_PIXELS:,}"
    assert _refused_in_one_line(code, err, "plan", (limit,)), err
    assert all(f"photo {f.name}.jpg declares 12,000 x 12,000 pixels" in err for f in frames), err
