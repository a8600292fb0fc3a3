"""Finding the capture that came with a scan (`loading.attach_capture` moves it into the world frame).

Where to look: the folder (or extracted zip) the user gave, else the mesh file's own folder, there only as
deep as the formats' layouts go (detect.BESIDE_DEPTH). Only that folder is read
(services.core.ingest.capture.detect bounds the walk), so a capture is never taken from elsewhere.
"""

from __future__ import annotations

import logging
from pathlib import Path

from services.core.ingest.capture.detect import BESIDE_DEPTH, MAX_DEPTH, find_capture
from services.core.ingest.capture.model import Capture

log = logging.getLogger(__name__)

def capture_root(given: Path) -> Path:
    """The folder a capture of `given` (a scan file, its folder, or an extracted zip's folder) must lie in."""
    return given if given.is_dir() else given.parent


def capture_near(given: Path) -> Capture | None:
    """The capture found for `given` (a scan file, its folder, or an extracted zip's folder), source frame."""
    root = capture_root(given)
    try:
        return find_capture(root, MAX_DEPTH if given.is_dir() else BESIDE_DEPTH)
    except (OSError, ValueError) as e:  # an unreadable capture never stops the scan from loading
        log.warning("%s: capture not read (%s)", root, e)
        return None


def capture_files_beside(mesh_file: Path, mesh_suffixes: tuple[str, ...]) -> list[Path]:
    """Files to store with a single mesh file that has a capture beside it (the folder's files as deep as the
    capture was looked for, without the other meshes there); [] when there is no capture beside it."""
    from services.core.ingest.capture.detect import list_files

    folder = mesh_file.parent
    if find_capture(folder, BESIDE_DEPTH) is None:
        return []
    return [
        p for p in list_files(folder, BESIDE_DEPTH) if p == mesh_file or p.suffix.lower() not in mesh_suffixes
    ]
