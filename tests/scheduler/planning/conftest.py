"""Fixtures of the planning tests."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def shared_scenes(scenes_dir: Path) -> Path:
    """The real scans beside the repository (`<repo>/../shared/scenes`, from tests/conftest.py)."""
    return scenes_dir
