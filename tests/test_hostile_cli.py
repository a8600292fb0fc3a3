"""Hostile scan files on the command line (issue 11, item 15): `omnidata plan` and `omnidata generate` refuse
each with one line on stderr and exit status 2, before anything is written."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli import main
from tests.hostile_corpus import HOSTILE_FILES


def _write(tmp_path: Path, case: str) -> Path:
    filename, make, _needles = HOSTILE_FILES[case]
    path = tmp_path / case / filename
    path.parent.mkdir(parents=True)
    path.write_bytes(make())
    return path


def test_plan_refuses_every_hostile_file_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
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


@pytest.mark.parametrize("case", ["zip_bad_crc", "zip_corrupt_deflate", "obj_truncated_mid_token", "texture_dotdot_path"])
def test_generate_refuses_corrupt_files_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    out = tmp_path / "out"
    code = main(["generate", str(_write(tmp_path, case)), "--out", str(out), "--no-progress"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("omnidata generate: error: "), lines
    assert any(n in lines[0] for n in HOSTILE_FILES[case][2]) and "Traceback" not in lines[0]
    assert not out.exists()
