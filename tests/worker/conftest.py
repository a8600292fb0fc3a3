"""Fixtures of the worker tests: the scan files they render."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def banana_path(scenes_dir: Path) -> Path:
    return scenes_dir / "ycb_banana" / "textured_simple_reoriented.obj"


@pytest.fixture(scope="session")
def bunny_path(scenes_dir: Path) -> Path:
    return scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
