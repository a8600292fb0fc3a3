"""Checks every capture reader applies to each frame; a failing frame gets one message and the others go on.

Paths: a reader names files relative to the capture root (the upload), and `inside` refuses any that would be
read outside it (absolute paths, '..', links leading out), so no capture makes us open another file.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np
from numpy.typing import ArrayLike

from services.core.ingest.capture.model import Capture, CaptureFrame
from services.core.ingest.capture.photos import PhotoRefused, photo_header

# |R^T R - I| and |det R - 1| beyond this: not a rotation (re-orthonormalised below it)
ROTATION_TOLERANCE = 1e-3
MAX_FRAMES = 100_000
MAX_TEXT_BYTES = 256 << 20  # a pose/camera text or JSON file larger than this is refused unread


def inside(root: Path, relative: str) -> Path | None:
    """`root / relative` when it names a path inside root (after following links), else None."""
    rel = relative.replace("\\", "/")
    pure = PurePosixPath(rel)
    if not rel or pure.is_absolute() or (len(rel) > 1 and rel[1] == ":") or ".." in pure.parts:
        return None
    base = root.resolve()
    target = (base / pure).resolve()
    return target if target == base or base in target.parents else None


def read_text(path: Path, root: Path) -> str:
    """Text of a file inside root (size-capped); OSError/ValueError say why it cannot be read."""
    if inside(root, os.path.relpath(path, root)) is None:
        raise ValueError(f"{path.name} lies outside the capture")
    if path.stat().st_size > MAX_TEXT_BYTES:
        raise ValueError(f"{path.name} is larger than {MAX_TEXT_BYTES >> 20} MiB")
    return path.read_text(errors="replace")


def read_capture_json(root: Path, path: Path, fmt: str) -> tuple[object, Capture | None]:
    """(the parsed JSON of a capture file, None), or (None, an empty `fmt` capture naming why it is
    unreadable)."""
    try:
        return json.loads(read_text(path, root)), None
    except (OSError, ValueError) as e:
        return None, Capture(fmt, root, (), (f"{path.name}: not readable JSON ({e})",))
    except RecursionError:  # json's decoder recurses once per nesting level
        return None, Capture(fmt, root, (), (f"{path.name}: not readable JSON (nested too deep)",))


def rigid_pose(matrix: ArrayLike) -> tuple[np.ndarray | None, str | None]:
    """(4x4 camera_to_world with an exact rotation, None) or (None, what is wrong with it)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        return None, "pose is not a matrix of numbers"
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        return None, f"pose has shape {list(m.shape)}, expected 4x4"
    if not np.isfinite(m).all():
        return None, "pose has NaN or infinite values (a lost frame, as BundleFusion and ScanNet write them)"
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return None, f"pose's last row is {m[3].tolist()}, not [0, 0, 0, 1]"
    R = m[:3, :3]
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        return None, f"pose's 3x3 part is not a rotation (det {det:.4g}, |R^T R - I| {ortho:.3g})"
    u, _, vt = np.linalg.svd(R)  # remove rounding noise of text files
    m = m.copy()
    m[:3, :3] = u @ vt
    return m, None


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the image header, None when it is not a readable image or over the photo budget
    (the frame's check then says which)."""
    try:
        return photo_header(path)
    except PhotoRefused:
        return None


@dataclass
class FrameCollector:
    """Builds a reader's frames, checking each and keeping one message per problem."""

    root: Path
    frames: list[CaptureFrame] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    check_images: bool = True

    def problem(self, message: str) -> None:
        """Record a problem (the frame it names is skipped)."""
        self.problems.append(message)

    def add(
        self, name: str, image: str | None, pose: ArrayLike,
        *,
        K: ArrayLike | None = None, size: tuple[int, int] | None = None, distortion: str = "none",
        params: tuple[float, ...] = (),
    ) -> None:
        """Check one frame and keep it when it is good. `size`: the (width, height) the camera says; None
        reads it from the image header."""
        if len(self.frames) >= MAX_FRAMES:
            if len(self.problems) == 0 or not self.problems[-1].startswith("more than"):
                self.problem(f"more than {MAX_FRAMES} frames: the rest are ignored")
            return
        c2w, why = rigid_pose(pose)
        if c2w is None:
            self.problem(f"frame {name}: {why}; skipped")
            return
        if image is not None:
            path = inside(self.root, image)
            if path is None:
                self.problem(f"frame {name}: image path {image!r} points outside the capture; skipped")
                return
            if not path.is_file():
                self.problem(f"frame {name}: image {image} is missing; skipped")
                return
            if self.check_images or size is None:
                try:
                    actual = photo_header(path)
                except PhotoRefused as e:
                    self.problem(f"frame {name}: {e}; skipped")
                    return
                if actual is None:
                    self.problem(f"frame {name}: {image} is not a readable image; skipped")
                    return
                if size is not None and tuple(size) != actual:
                    self.problem(
                        f"frame {name}: image {image} is {actual[0]}x{actual[1]} pixels but its camera says "
                        f"{size[0]}x{size[1]}; skipped"
                    )
                    return
                size = actual
        if K is not None:
            K = np.asarray(K, dtype=np.float64)
            if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
                self.problem(
                    f"frame {name}: intrinsics are not a 3x3 matrix with positive focal lengths; skipped"
                )
                return
        if not all(np.isfinite(params)):
            self.problem(f"frame {name}: distortion parameters are not finite; skipped")
            return
        width, height = size if size is not None else (None, None)
        self.frames.append(CaptureFrame(name, image, width, height, K, distortion, tuple(params), c2w))

    def add_pose_file(
        self, name: str, image: str, pose_file: Path,
        *,
        shown_as: str, K: ArrayLike | None = None, size: tuple[int, int] | None = None,
    ) -> None:
        """Add a frame whose pose is a text file of 16 numbers (a row-major 4x4), or record why it is skipped
        (`shown_as`: the pose file as the message names it)."""
        try:
            pose = np.array([float(x) for x in read_text(pose_file, self.root).split()], dtype=np.float64)
        except ValueError:
            self.problem(f"frame {name}: {shown_as} is not 16 numbers; skipped")
            return
        if pose.size != 16:
            self.problem(f"frame {name}: {shown_as} has {pose.size} numbers, expected 16 (4x4); skipped")
            return
        self.add(name, image, pose.reshape(4, 4), K=K, size=size)
