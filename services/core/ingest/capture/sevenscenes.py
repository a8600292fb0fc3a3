"""The 7-Scenes / 3DMatch / BundleFusion layout: `frame-NNNNNN.color.{jpg,png}` + `frame-NNNNNN.pose.txt` (4x4
camera-to-world, metres, OpenCV axes) per frame, with `camera-intrinsics.txt` (3x3 K) or BundleFusion's
`info.txt` (`m_calibrationColorIntrinsic = fx 0 cx 0 0 fy cy 0 ...`, `m_colorWidth`, `m_colorHeight`).

The intrinsics files put pixel centres at integer coordinates (OpenCV), so the principal point moves by +0.5.
Lost frames (BundleFusion writes -inf poses) are reported and skipped. No distortion is given by these
formats.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from services.core.ingest.capture.checks import FrameCollector, read_text
from services.core.ingest.capture.model import Capture

FRAME_RE = re.compile(r"^(frame-\d+)\.pose\.txt$")
COLOR_SUFFIXES = (".color.jpg", ".color.png")


def frame_folders(root: Path, files: list[Path]) -> list[Path]:
    """Folders (in order) holding `frame-*.pose.txt` files."""
    return sorted({p.parent for p in files if FRAME_RE.match(p.name)})


def _intrinsics(
    root: Path, folder: Path, notes: list[str]
) -> tuple[np.ndarray, tuple[int, int] | None] | str:
    """(K with pixel centres at +0.5, size or None) from the nearest intrinsics file at or above folder, or
    why not."""
    here = folder
    while True:
        intr, info = here / "camera-intrinsics.txt", here / "info.txt"
        if intr.is_file():
            try:
                K = np.array([float(x) for x in read_text(intr, root).split()], dtype=np.float64)
            except ValueError as e:
                return f"{intr.name}: not a 3x3 matrix of numbers ({e})"
            if K.size != 9:
                return f"{intr.name}: expected 9 numbers (3x3 K), found {K.size}"
            notes.append(f"intrinsics from {intr.relative_to(root)}")
            K = K.reshape(3, 3)
            K[:2, 2] += 0.5
            return K, None
        if info.is_file():
            return _bundlefusion_info(root, info, notes)
        if here == root or root not in here.parents:
            return "no camera-intrinsics.txt or info.txt (BundleFusion) found beside the frames"
        here = here.parent


def _bundlefusion_info(
    root: Path, info: Path, notes: list[str]
) -> tuple[np.ndarray, tuple[int, int] | None] | str:
    values: dict[str, str] = {}
    for line in read_text(info, root).splitlines():
        key, sep, value = line.partition("=")
        if sep:
            values[key.strip()] = value.strip()
    try:
        m = np.array([float(x) for x in values["m_calibrationColorIntrinsic"].split()], dtype=np.float64)
        size = (int(values["m_colorWidth"]), int(values["m_colorHeight"]))
    except (KeyError, ValueError) as e:
        return f"{info.name}: needs m_calibrationColorIntrinsic, m_colorWidth and m_colorHeight ({e})"
    if m.size != 16:
        return f"{info.name}: m_calibrationColorIntrinsic has {m.size} numbers, expected 16 (4x4)"
    K = m.reshape(4, 4)[:3, :3].copy()
    K[:2, 2] += 0.5
    notes.append(f"intrinsics from {info.relative_to(root)} (colour camera, {size[0]}x{size[1]})")
    return K, size


def read_sevenscenes(root: Path, files: list[Path]) -> Capture:
    """Every frame of the layout under root (see the module docstring); `files`: the files found under
    root."""
    col = FrameCollector(root)
    notes: list[str] = []
    by_folder: dict[Path, list[Path]] = {}
    for p in files:
        if FRAME_RE.match(p.name):
            by_folder.setdefault(p.parent, []).append(p)
    for folder in sorted(by_folder):
        found = _intrinsics(root, folder, notes)
        if isinstance(found, str):
            col.problem(
                f"{folder.relative_to(root) if folder != root else '.'}: {found}; its frames are skipped"
            )
            continue
        K, size = found
        for pose_file in sorted(by_folder[folder]):
            stem = FRAME_RE.match(pose_file.name).group(1)  # type: ignore[union-attr]
            name = (pose_file.parent / stem).relative_to(root).as_posix()
            image = next((pose_file.parent / (stem + s) for s in COLOR_SUFFIXES
                          if (pose_file.parent / (stem + s)).is_file()), None)
            if image is None:
                col.problem(f"frame {name}: no {stem}.color.jpg or .color.png beside its pose; skipped")
                continue
            col.add_pose_file(
                name, image.relative_to(root).as_posix(), pose_file, shown_as=pose_file.name, K=K, size=size
            )
    return Capture("7scenes", root, tuple(col.frames), tuple(col.problems), notes=tuple(dict.fromkeys(notes)))
