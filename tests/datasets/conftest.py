"""Small real jobs (the embedded `omnidata generate`, 32 px renders of the banana) that the dataset tests
read."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import GeneratedRun
from tests.fixtures.cli import TRAJECTORY
from tests.fixtures.cli import generate_output as generate


@pytest.fixture(scope="session")
def small_job(tiny_banana: GeneratedRun) -> Path:
    """2 points x 2 wide-baseline views of the banana, every default cue, component 'tiny' (read only)."""
    return tiny_banana.out


@pytest.fixture(scope="session")
def trajectory_job(tmp_path_factory: pytest.TempPathFactory, scenes_dir: Path) -> Path:
    """One trajectory (a few frames) around the banana, every default cue."""
    return generate(
        scenes_dir / "ycb_banana", tmp_path_factory.mktemp("traj") / "banana", TRAJECTORY, "traj", 3
    )
