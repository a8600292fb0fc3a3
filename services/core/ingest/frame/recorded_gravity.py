"""Gravity a capture recorded beside its scan: the strongest evidence of up there is.

Frames: the vector is read in the scan's source frame (the file lies beside the mesh it describes). Formats:
- `gravity-direction.txt` (Microsoft 7-Scenes, andyzeng/tsdf-fusion-python): three numbers, the direction
  gravity pulls (down) in the frame of the fused mesh, i.e. its first camera's frame.
- `closed_loop_trajectory.csv` (Project Aria Machine Perception Services): a CSV whose columns
  `gravity_x_world`, `gravity_y_world`, `gravity_z_world` give gravity (m/s^2, down) in the MPS world frame,
  the frame of its semi-dense points (`global_points`); the mean over the rows read.
Up is gravity's opposite. An unreadable or degenerate file is reported and ignored, never a reason to refuse
the scan.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

GRAVITY_FILES = ("gravity-direction.txt", "closed_loop_trajectory.csv")
MAX_BYTES = 4096  # gravity-direction.txt: three numbers; anything larger is not this format
TRAJECTORY_ROWS = 1000  # a trajectory's gravity is one vector repeated: its first rows suffice
GRAVITY_COLUMNS = ("gravity_x_world", "gravity_y_world", "gravity_z_world")


@dataclass(frozen=True)
class RecordedUp:
    """Up (unit vector, source frame) as a recording gave it, and the file it came from."""

    up: np.ndarray
    source: str


def recorded_gravity_files(folder: Path) -> list[Path]:
    """The recorded-gravity files in `folder` (they go with the mesh wherever it is stored)."""
    return [folder / n for n in GRAVITY_FILES if (folder / n).is_file() and not (folder / n).is_symlink()]


def read_recorded_up(folder: Path) -> RecordedUp | None:
    """The recorded up in `folder` (see the module docstring), None when absent or unusable."""
    for name in GRAVITY_FILES:
        path = folder / name
        if not path.is_file() or path.is_symlink():
            continue
        try:
            g = _trajectory_gravity(path) if path.suffix == ".csv" else _vector(path)
        except (OSError, ValueError, IndexError, UnicodeDecodeError) as e:
            log.warning("%s: not read (%s)", path, e)
            continue
        n = float(np.linalg.norm(g)) if g.shape == (3,) and np.isfinite(g).all() else 0.0
        if n < 1e-6:
            log.warning("%s: expected one non-zero 3-vector, found %s", path, g.tolist())
            continue
        return RecordedUp(0.0 - g / n, name)  # 0.0 -: no negative zeros in what is shown
    return None


def _vector(path: Path) -> np.ndarray:
    if path.stat().st_size > MAX_BYTES:
        raise ValueError(f"larger than {MAX_BYTES} bytes")
    return np.array([float(x) for x in path.read_text(encoding="utf-8").split()], dtype=np.float64)


def _trajectory_gravity(path: Path) -> np.ndarray:
    """The mean of the gravity columns over a trajectory CSV's first `TRAJECTORY_ROWS` rows."""
    with open(path, encoding="utf-8", newline="") as f:
        rows = csv.reader(f)
        header = [h.strip() for h in next(rows, [])]
        if not all(c in header for c in GRAVITY_COLUMNS):
            raise ValueError(f"no columns {', '.join(GRAVITY_COLUMNS)}")
        cols = [header.index(c) for c in GRAVITY_COLUMNS]
        values = [[float(row[i]) for i in cols] for row, _ in zip(rows, range(TRAJECTORY_ROWS), strict=False)]
    if not values:
        raise ValueError("no rows")
    return np.asarray(values, dtype=np.float64).mean(axis=0)
