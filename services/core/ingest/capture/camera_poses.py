"""The Omnidata annotator's `camera_poses.json`: a list of cameras, each a `location` and the wxyz
`quaternion` (or `rotation_quaternion`) of the Blender camera object (looking down its -z, y up), in the
scan's frame; optionally `camera_uuid`/`uuid`, `field_of_view_rads` with `resolution`, and an `image` path.
Without images it is a capture of poses only: views at those cameras take RGB from the mesh.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from services.core.domain.camera import CV_TO_BLENDER, quaternion_wxyz_to_rotation
from services.core.ingest.capture.checks import FrameCollector, read_capture_json
from services.core.ingest.capture.model import Capture


def _pose(entry: Mapping[str, object]) -> np.ndarray | None:
    loc = entry.get("location")
    q = entry.get("quaternion", entry.get("rotation_quaternion"))
    try:
        loc_a = np.asarray(loc, dtype=np.float64)
        q_a = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if loc_a.shape != (3,) or q_a.shape != (4,):
        return None
    m = np.full((4, 4), np.nan)
    m[3] = [0.0, 0.0, 0.0, 1.0]
    if np.isfinite(q_a).all() and abs(np.linalg.norm(q_a) - 1.0) < 1e-3:
        m[:3, :3] = quaternion_wxyz_to_rotation(q_a)
    m[:3, 3] = loc_a
    return m @ CV_TO_BLENDER  # Blender camera axes -> OpenCV


def read_camera_poses(root: Path, path: Path) -> Capture:
    """The cameras of one camera_poses.json (see the module docstring)."""
    col = FrameCollector(root)
    doc, unreadable = read_capture_json(root, path, "camera_poses")
    if unreadable is not None:
        return unreadable
    entries = doc.get("cameras", doc.get("poses")) if isinstance(doc, dict) else doc
    if not isinstance(entries, list):
        return Capture("camera_poses", root, (), (f"{path.name}: expected a list of cameras",))
    base = path.parent.relative_to(root).as_posix()
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            col.problem(f"camera {i}: not an object; skipped")
            continue
        name = str(entry.get("camera_uuid") or entry.get("uuid") or i)
        pose = _pose(entry)
        if pose is None:
            col.problem(f"camera {name}: needs location [x, y, z] and a wxyz quaternion; skipped")
            continue
        image, K, size = entry.get("image"), None, None
        fov, res = entry.get("field_of_view_rads"), entry.get("resolution")
        if isinstance(fov, int | float) and isinstance(res, int) and 0 < fov < math.pi and res > 0:
            f = res / 2.0 / math.tan(fov / 2.0)
            K, size = np.array([[f, 0, res / 2.0], [0, f, res / 2.0], [0, 0, 1.0]]), (res, res)
        if isinstance(image, str):
            image = image if base in ("", ".") else f"{base}/{image}"
        else:
            image = None
        if image is not None and K is None:
            col.problem(f"camera {name}: an image without field_of_view_rads and resolution; skipped")
            continue
        col.add(name, image, pose, K=K, size=size)
    return Capture("camera_poses", root, tuple(col.frames), tuple(col.problems),
                   notes=(f"{path.relative_to(root).as_posix()}: Blender camera axes turned to OpenCV",))
