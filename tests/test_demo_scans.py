"""`make demo` stands alone: every scan it renders ships in the repository (examples/scans), matches the
checksums and license note of its SOURCE.md, and loads as a space (textured banana, untextured bunny)."""

from __future__ import annotations

import hashlib
import re
import shlex
from pathlib import Path

import pytest

from services.core.ingest.loading import load_space
from tests.conftest import REPO_ROOT


def demo_inputs() -> list[Path]:
    """The SPACE arguments of the Makefile's demo target, with its default SCENES."""
    makefile = (REPO_ROOT / "Makefile").read_text()
    scenes = re.search(r"^SCENES \?= (\S+)$", makefile, re.M)
    command = re.search(r"^demo:.*\n\t\$\(BIN\)/omnidata generate (.+?)\s+--out", makefile, re.M | re.S)
    assert scenes and command, "the Makefile's demo target changed shape"
    spaces = command.group(1).rstrip(" \\\t\n")  # up to the line continuation before --out
    args = shlex.split(spaces.replace("$(SCENES)", scenes.group(1)))
    return [REPO_ROOT / a for a in args]


def test_demo_renders_only_scans_inside_the_repository() -> None:
    inputs = demo_inputs()
    assert len(inputs) == 2
    for path in inputs:
        assert path.exists(), path
        assert path.resolve().is_relative_to(REPO_ROOT), f"{path} is outside the repository"


@pytest.mark.parametrize("path", demo_inputs(), ids=lambda p: p.name)
def test_demo_scan_matches_its_source_note_and_loads(path: Path) -> None:
    folder = path if path.is_dir() else path.parent
    note = (folder / "SOURCE.md").read_text()
    assert "## License" in note and "## Origin" in note
    listed = dict(re.findall(r"^\| `([^`]+)` \| [\d,]+ \| `([0-9a-f]{64})` \|$", note, re.M))
    shipped = {p.name for p in folder.iterdir() if p.name != "SOURCE.md"}
    assert set(listed) == shipped, "every shipped file is listed with its checksum"
    for name, digest in listed.items():
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name
    loaded = load_space(path)
    assert loaded.face_count > 10_000
    assert loaded.has_texture == (folder.name == "ycb_banana")
