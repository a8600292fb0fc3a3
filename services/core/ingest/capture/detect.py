"""Finding a capture in an upload: the folder (or extracted zip) that holds the scan, or the scan's own folder.

The walk is bounded (depth, number of entries) and never follows links out of the root, so pointing at a mesh in
a big folder costs little and reads nothing outside it. The first format found wins, in this order:
transforms.json, a COLMAP model, a ScanNet export, the 7-Scenes/BundleFusion layout, camera_poses.json.
"""

from __future__ import annotations

import os
from pathlib import Path

from services.core.ingest.capture.camera_poses import read_camera_poses
from services.core.ingest.capture.colmap import model_folders, read_colmap
from services.core.ingest.capture.model import Capture
from services.core.ingest.capture.scannet import export_folders, read_scannet
from services.core.ingest.capture.sevenscenes import FRAME_RE, read_sevenscenes

MAX_DEPTH = 4
MAX_ENTRIES = 400_000
FORMATS = ("transforms", "colmap", "scannet", "7scenes", "camera_poses")


def list_files(root: Path, max_depth: int = MAX_DEPTH, max_entries: int = MAX_ENTRIES) -> list[Path]:
    """Regular files under root (no links, no hidden entries), at most max_depth folders deep."""
    out: list[Path] = []
    seen = 0
    stack = [(root, 0)]
    while stack:
        folder, depth = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            seen += 1
            if seen > max_entries:
                return sorted(out)
            if entry.name.startswith(".") or entry.name == "__MACOSX" or entry.is_symlink():
                continue
            if entry.is_dir(follow_symlinks=False):
                if depth < max_depth:
                    stack.append((Path(entry.path), depth + 1))
            elif entry.is_file(follow_symlinks=False):
                out.append(Path(entry.path))
    return sorted(out)


def find_capture(root: str | Path) -> Capture | None:
    """The capture under `root` (a folder), or None when it holds none of the known formats."""
    root = Path(root)
    if not root.is_dir():
        return None
    files = list_files(root)
    transforms = [p for p in files if p.name == "transforms.json"]
    if transforms:
        return read_transforms_first(root, transforms)
    models = model_folders(files)
    if models:
        return read_colmap(root, models[0])
    exports = export_folders(files)
    if exports:
        return read_scannet(root, exports[0])
    if any(FRAME_RE.match(p.name) for p in files):
        return read_sevenscenes(root, files)
    poses = [p for p in files if p.name == "camera_poses.json"]
    if poses:
        return read_camera_poses(root, poses[0])
    return None


def read_transforms_first(root: Path, paths: list[Path]) -> Capture:
    """The shallowest transforms.json (nerfstudio writes others for splits)."""
    from services.core.ingest.capture.transforms import read_transforms

    return read_transforms(root, min(paths, key=lambda p: (len(p.relative_to(root).parts), str(p))))
