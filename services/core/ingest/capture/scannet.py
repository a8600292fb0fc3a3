"""ScanNet exports (the SensReader's output): `color/<i>.jpg`, `pose/<i>.txt` (4x4 camera-to-world, metres,
OpenCV axes; -inf for frames the tracker lost) and `intrinsic/intrinsic_color.txt` (4x4, pixel centres at
integers: +0.5 here). `depth/` and the depth intrinsics are not needed: depth comes from the mesh.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.core.ingest.capture.checks import FrameCollector, read_text
from services.core.ingest.capture.model import Capture


def export_folders(files: list[Path]) -> list[Path]:
    """Folders holding a ScanNet export (pose/ and intrinsic/intrinsic_color.txt)."""
    return sorted(
        {
            p.parent.parent
            for p in files
            if p.name == "intrinsic_color.txt"
            and p.parent.name == "intrinsic"
            and (p.parent.parent / "pose").is_dir()
        }
    )


def _numbers(path: Path, root: Path) -> np.ndarray:
    return np.array([float(x) for x in read_text(path, root).split()], dtype=np.float64)


def read_scannet(root: Path, folder: Path) -> Capture:
    """The frames of one ScanNet export folder, in frame-number order."""
    col = FrameCollector(root)
    try:
        m = _numbers(folder / "intrinsic" / "intrinsic_color.txt", root)
    except (OSError, ValueError) as e:
        return Capture("scannet", root, (), (f"intrinsic/intrinsic_color.txt: not readable ({e})",))
    if m.size != 16:
        return Capture(
            "scannet", root, (), (f"intrinsic/intrinsic_color.txt: {m.size} numbers, expected 16",)
        )
    K = m.reshape(4, 4)[:3, :3].copy()
    K[:2, 2] += 0.5
    poses = [p for p in (folder / "pose").iterdir() if p.suffix == ".txt" and p.stem.isdigit()]
    prefix = folder.relative_to(root).as_posix()
    prefix = "" if prefix == "." else prefix + "/"
    for pose_file in sorted(poses, key=lambda p: int(p.stem)):
        i = pose_file.stem
        image = next(
            (
                f"{prefix}color/{i}{ext}"
                for ext in (".jpg", ".png")
                if (folder / "color" / f"{i}{ext}").is_file()
            ),
            None,
        )
        if image is None:
            col.problem(f"frame {i}: color/{i}.jpg is missing; skipped")
            continue
        col.add_pose_file(i, image, pose_file, shown_as=f"pose/{i}.txt", K=K)
    return Capture("scannet", root, tuple(col.frames), tuple(col.problems),
                   notes=(f"ScanNet export in {prefix or './'}",))
