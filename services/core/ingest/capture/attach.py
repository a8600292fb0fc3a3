"""Attaching the capture found with a scan to the loaded space, in its world frame.

Where to look: the folder (or extracted zip) the user gave, else the mesh file's own folder, there only as deep as
the formats' layouts go (detect.BESIDE_DEPTH). Only that folder is read (services.core.ingest.capture.detect bounds
the walk), so a capture is never taken from elsewhere.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.core.ingest.capture.detect import BESIDE_DEPTH, MAX_DEPTH, find_capture
from services.core.ingest.capture.model import Capture

if TYPE_CHECKING:  # loading.py imports this module
    from services.core.ingest.loading import LoadedSpace

log = logging.getLogger(__name__)

CAPTURE_UP_WARN_DEG = 10.0  # the cameras' up this far from the scan's: the levelling (or the capture) is suspect


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


def attach_capture(loaded: LoadedSpace, capture: Capture | None) -> LoadedSpace:
    """`loaded` (a LoadedSpace) with `capture` (source frame) moved into its world frame, when there is one."""
    if capture is None:
        return loaded
    for problem in capture.problems[:20]:
        log.warning("%s capture: %s", capture.format, problem)
    if capture.problems:  # shown by `omnidata plan` and kept in job.json with the other warnings
        shown = "; ".join(capture.problems[:5]) + (f"; and {len(capture.problems) - 5} more" if len(capture.problems) > 5 else "")
        note = f"{capture.format} capture: {len(capture.frames)} frames read, {len(capture.problems)} problems: {shown}"
        loaded = dataclasses.replace(loaded, warnings=(*loaded.warnings, note))
    world = capture.in_world(loaded.source_to_world)
    up = world.mean_up()  # the cameras' evidence of up, checked against the scan's levelling
    if up is not None:
        angle = float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
        note = f"the cameras' up (right axes level) is {angle:.1f} deg from the scan's up"
        world = dataclasses.replace(world, notes=(*world.notes, note), up_angle_deg=angle)
        if angle > CAPTURE_UP_WARN_DEG:
            loaded = dataclasses.replace(loaded, warnings=(*loaded.warnings, f"{note}: check the levelling"))
    return dataclasses.replace(loaded, capture=world)


def capture_files_beside(mesh_file: Path, mesh_suffixes: tuple[str, ...]) -> list[Path]:
    """Files to store with a single mesh file that has a capture beside it (the folder's files as deep as the
    capture was looked for, without the other meshes there); [] when there is no capture beside it."""
    from services.core.ingest.capture.detect import list_files

    folder = mesh_file.parent
    if find_capture(folder, BESIDE_DEPTH) is None:
        return []
    return [p for p in list_files(folder, BESIDE_DEPTH) if p == mesh_file or p.suffix.lower() not in mesh_suffixes]
