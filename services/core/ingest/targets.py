"""A target to steer a dataset towards: the camera distributions of a posed capture or of another dataset.

Three kinds of input, read without rendering:
- a posed capture (services.core.ingest.capture: COLMAP, transforms.json, ScanNet, 7-Scenes,
  camera_poses.json) in the world frame of its scan: fov is the widest square the photo fills (as capture
  views use it);
- a folder of point_info JSONs (ours, or the public Omnidata release's: camera_location and
  camera_rotation_final when there is no world_to_camera): fov, pitch, roll, distance, and height above the
  lowest point;
- a CSV with a header naming any of fov_deg, pitch_deg, roll_deg, height_m, distance_m (others ignored).
Heights of a capture need the floor of its scan; the caller gives it (the capture alone has no floor).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.core.domain.camera import world_to_camera_from_blender
from services.core.domain.steering import camera_distributions
from services.core.ingest.capture import Capture

TARGET_COLUMNS = ("fov_deg", "pitch_deg", "roll_deg", "height_m", "distance_m")
MAX_TARGET_FILES = 200_000  # point_info files read at most (a big release: sample it first)


class TargetError(ValueError):
    """A target that cannot be read, with the reason."""


@dataclass(frozen=True)
class Target:
    """A target's distributions (steering.DISTRIBUTIONS names) and, when posed in a scan's world frame, its
    camera centres (world metres)."""

    source: str
    values: dict[str, np.ndarray]
    centres: np.ndarray | None = None


def capture_target(capture: Capture, floor_z: float | None) -> Target:
    """A world-frame capture's fov, pitch and roll, and its heights above `floor_z` when given."""
    frames = [f for f in capture.frames if f.K is not None]
    if not frames:
        raise TargetError(f"the {capture.format} capture has no frame with intrinsics")
    W = np.stack([f.world_to_camera for f in frames])
    fov = np.array([f.inscribed_fov() for f in frames])
    values = camera_distributions(W, fov, 0.0 if floor_z is None else floor_z)
    if floor_z is None:
        del values["height_m"]
    return Target(f"capture:{capture.format}", values, np.stack([f.center for f in frames]))


def _point_info_pose(info: dict[str, object]) -> np.ndarray:
    if "world_to_camera" in info:
        return np.asarray(info["world_to_camera"], dtype=np.float64)
    return world_to_camera_from_blender(np.asarray(info["camera_location"], dtype=np.float64),
                                        np.asarray(info["camera_rotation_final"], dtype=np.float64))


def point_info_target(folder: Path) -> Target:
    """The views of a folder of point_info JSONs (searched recursively); height above their lowest point."""
    files = sorted(folder.rglob("*point_info*.json"))[:MAX_TARGET_FILES]
    if not files:
        raise TargetError(f"no point_info JSON under {folder}")
    W, fov, dist, low = [], [], [], []
    for path in files:
        try:
            info = json.loads(path.read_text())
            W.append(_point_info_pose(info))
            fov.append(float(info["field_of_view_rads"]))
            dist.append(float(info.get("camera_distance", np.nan)))
            low.append(float(np.asarray(info["point_location"], dtype=np.float64)[2]))
        except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
            raise TargetError(f"{path.name}: not a point_info JSON ({e})") from e
    # the lowest point seen stands in for the floor, as steering.plan_floor_z does for a plan
    values = camera_distributions(np.stack(W), np.array(fov), min(low))
    values["distance_m"] = np.array(dist)
    return Target("point_info", values)


def csv_target(path: Path) -> Target:
    """The columns of TARGET_COLUMNS in a CSV with a header (rows with an empty cell skip that column)."""
    try:
        with path.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise TargetError(f"{path.name}: cannot read the CSV ({e})") from e
    names = [c for c in TARGET_COLUMNS if rows and c in rows[0]]
    if not names:
        raise TargetError(f"{path.name}: no column named any of {', '.join(TARGET_COLUMNS)}")
    values = {}
    for name in names:
        try:
            values[name] = np.array([float(r[name]) for r in rows if (r.get(name) or "").strip()])
        except ValueError as e:
            raise TargetError(f"{path.name}: column {name}: {e}") from e
    return Target("csv", values)
