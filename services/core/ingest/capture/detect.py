"""Finding a capture in an upload: the folder (or extracted zip) that holds the scan, or the scan's own
folder.

The walk is bounded (depth, number of entries) and never follows links out of the root, so pointing at a mesh
in a big folder costs little and reads nothing outside it. The first format found wins, in this order:
transforms.json, a COLMAP model, a ScanNet export, the 7-Scenes/BundleFusion layout, camera_poses.json.
A folder (or zip) the user gave is walked MAX_DEPTH folders deep; beside a single mesh file only BESIDE_DEPTH,
the deepest the formats' own layouts go (COLMAP's sparse/0/): a scan saved in a busy folder (a home,
Downloads, /tmp) does not take a capture from someone else's project further down.

Within `captures_kept()`, what was read is kept, keyed by the folder's listing (each file's path, size, times
and inode): `generate` looks for the capture beside a scan five times (checksum, validation, loading, packing,
registering), and reading the 7-Scenes kitchen's 500 poses and photo headers costs ~0.11 CPU-s each time. Only
a command that reads its inputs once holds it (a long-lived process, the API, reads every time: a file
rewritten with the same size within a clock tick keeps its stat).
"""

from __future__ import annotations

import contextlib
import os
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path

from services.core.ingest.capture.camera_poses import read_camera_poses
from services.core.ingest.capture.colmap import model_folders, read_colmap
from services.core.ingest.capture.model import Capture
from services.core.ingest.capture.scannet import export_folders, read_scannet
from services.core.ingest.capture.sevenscenes import FRAME_RE, read_sevenscenes

MAX_DEPTH = 4
BESIDE_DEPTH = 2  # a capture next to a single mesh file: sparse/0/cameras.bin, frames/*.pose.txt, color/, ...
MAX_ENTRIES = 400_000
FORMATS = ("transforms", "colmap", "scannet", "7scenes", "camera_poses")
KEPT_CAPTURES = 8  # captures (or their absence) kept, the least recently asked for dropped first

_kept: OrderedDict[tuple, Capture | None] = OrderedDict()
_keeping = 0  # captures_kept() blocks entered and not left


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


def find_capture(root: str | Path, max_depth: int = MAX_DEPTH) -> Capture | None:
    """The capture under `root` (a folder, walked max_depth folders deep), or None when it holds none of the
    known formats (Capture is frozen: the one kept for an unchanged folder is handed out again)."""
    root = Path(root)
    if not root.is_dir():
        return None
    files = list_files(root, max_depth)
    key = _listing_key(root, files) if _keeping else None
    if key is not None and key in _kept:
        _kept.move_to_end(key)
        return _kept[key]
    capture = _read_capture(root, files)
    if key is not None:
        _kept[key] = capture
        while len(_kept) > KEPT_CAPTURES:
            _kept.popitem(last=False)
    return capture


@contextlib.contextmanager
def captures_kept() -> Iterator[None]:
    """Within it, find_capture keeps what it reads for the same, unchanged folder (module docstring)."""
    global _keeping
    _keeping += 1
    try:
        yield
    finally:
        _keeping -= 1
        if not _keeping:
            _kept.clear()


def _listing_key(root: Path, files: list[Path]) -> tuple | None:
    """What a capture read from `files` depends on, or None when a file vanished while listing (not kept)."""
    try:
        stats = tuple(
            (str(p), (st := p.stat()).st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino) for p in files
        )
    except OSError:
        return None
    return str(root), str(root.resolve()), stats  # the path as given too: the capture's root is kept as given


def _read_capture(root: Path, files: list[Path]) -> Capture | None:
    """The first known format among `files` (the module docstring's order), read."""
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
