"""Small real jobs (the embedded `omnidata generate`, 32 px renders of the banana) that the dataset tests read."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
WIDE = """
cameras: {mode: object, object_count: 6}
points: {count: 2, min_views: 2, max_views: 2}
views: {resolution: 32}
"""
TRAJECTORY = """
cameras: {mode: object, object_count: 6}
points: {count: 1, min_views: 2}
views: {resolution: 32, mode: trajectory, trajectory_max_frames: 5}
"""


def generate(scene: Path, out: Path, spec_text: str, name: str, seed: int) -> Path:
    """Run `omnidata generate` (every default cue) in a fresh interpreter; returns the output folder."""
    spec = out.parent / f"{name}.yaml"
    spec.write_text(spec_text)
    cmd = [sys.executable, "-m", "services.cli", "generate", str(scene), "--out", str(out), "--spec", str(spec),
           "--seed", str(seed), "--workers", "1", "--name", name, "--no-progress"]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    return out


@pytest.fixture(scope="session")
def small_job(tmp_path_factory: pytest.TempPathFactory, scenes_dir: Path) -> Path:
    """2 points x 2 wide-baseline views of the banana, every default cue, component 'tiny'."""
    return generate(scenes_dir / "ycb_banana", tmp_path_factory.mktemp("job") / "banana", WIDE, "tiny", 7)


@pytest.fixture(scope="session")
def trajectory_job(tmp_path_factory: pytest.TempPathFactory, scenes_dir: Path) -> Path:
    """One trajectory (a few frames) around the banana, every default cue."""
    return generate(scenes_dir / "ycb_banana", tmp_path_factory.mktemp("traj") / "banana", TRAJECTORY, "traj", 3)
