"""The posed-capture domain type: frames of real photographs with their cameras, in the scan's source frame.

Conventions (the same as services.core.domain.camera):
- `K` is 3x3 in pixels with the centre of pixel u at u + 0.5 (COLMAP's convention; readers of formats that put
  pixel centres at integers add 0.5 to the principal point);
- `camera_to_world` is 4x4 from OpenCV camera axes (x right, y down, z forward) to the scan's *source*
  coordinates (what `trimesh.load(scan, force="mesh")` gives), in source units; `Capture.in_world` moves every
  frame by the space's `source_to_world`, exactly as the mesh is moved;
- `distortion` names the model of the photo's lens, applied to normalised undistorted coordinates (x/z, y/z):
  "none"; "radial" (k1, k2: COLMAP SIMPLE_RADIAL/RADIAL); "opencv" (k1, k2, p1, p2[, k3]: COLMAP OPENCV and
  nerfstudio); "fisheye" (k1, k2, k3, k4: OpenCV's equidistant model, COLMAP OPENCV_FISHEYE).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.core.domain.capture_records import CaptureSummary
from services.core.domain.plan import frozen_array

DISTORTION_PARAMS = {"none": (0, 0), "radial": (1, 2), "opencv": (4, 5), "fisheye": (4, 4)}


class CaptureError(ValueError):
    """A capture that cannot be used at all (no readable frame), with a message for the user."""


@dataclass(frozen=True, eq=False)
class CaptureFrame:
    """One photograph and its camera. `image` is a path relative to the capture root (None: a pose without
    photo)."""

    name: str
    image: str | None
    width: int | None  # pixels of the photo (None only without an image and intrinsics)
    height: int | None
    K: np.ndarray | None  # 3x3 pixels, centre of pixel u at u + 0.5
    distortion: str
    distortion_params: tuple[float, ...]
    camera_to_world: np.ndarray  # 4x4, OpenCV camera axes -> source (or, after in_world, world) coordinates

    def __post_init__(self) -> None:
        object.__setattr__(self, "camera_to_world", frozen_array(self.camera_to_world, (4, 4)))
        if self.K is not None:
            object.__setattr__(self, "K", frozen_array(self.K, (3, 3)))
        lo, hi = DISTORTION_PARAMS.get(self.distortion, (-1, -1))
        if lo < 0:
            raise ValueError(
                f"unknown distortion model {self.distortion!r}; known: {', '.join(DISTORTION_PARAMS)}"
            )
        if not lo <= len(self.distortion_params) <= hi:
            raise ValueError(f"distortion {self.distortion!r} takes {lo}..{hi} parameters, "
                             f"got {len(self.distortion_params)}")
        object.__setattr__(self, "distortion_params", tuple(float(x) for x in self.distortion_params))

    @property
    def world_to_camera(self) -> np.ndarray:
        """4x4 inverse of camera_to_world (rigid)."""
        R, t = self.camera_to_world[:3, :3], self.camera_to_world[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> np.ndarray:
        """Camera centre in the frame's coordinates."""
        return np.asarray(self.camera_to_world[:3, 3])

    def inscribed_fov(self) -> float:
        """Field of view (radians) of the widest square pinhole view about the optical axis that the photo
        fills: twice the smallest angle from the axis to an image edge (distortion ignored: a small
        margin)."""
        if self.K is None or self.width is None or self.height is None:
            raise ValueError(f"frame {self.name}: no intrinsics")
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        half = min(cx / fx, (self.width - cx) / fx, cy / fy, (self.height - cy) / fy)
        return float(2.0 * np.arctan(max(half, 1e-6)))


@dataclass(frozen=True, eq=False)
class Capture:
    """The good frames of one capture (format, root folder) and one message per problem found while reading
    it."""

    format: str  # 7scenes | colmap | transforms | scannet | camera_poses
    root: Path  # folder every image path is relative to
    frames: tuple[CaptureFrame, ...]
    problems: tuple[str, ...] = ()
    frame_space: str = "source"  # source | world (after in_world)
    notes: tuple[str, ...] = field(default=())  # how the format was read (e.g. which intrinsics file)
    # angle between the cameras' up (mean_up) and world +Z, once in the world
    up_angle_deg: float | None = None

    @property
    def has_photos(self) -> bool:
        """True when the frames carry images with intrinsics."""
        return bool(self.frames) and all(f.image is not None and f.K is not None for f in self.frames)

    def image_path(self, frame: CaptureFrame) -> Path:
        """Absolute path of a frame's image (readers checked it stays inside the root)."""
        if frame.image is None:
            raise ValueError(f"frame {frame.name} has no image")
        return self.root / frame.image

    def in_world(self, source_to_world: np.ndarray) -> Capture:
        """The capture with every camera moved by the space's source_to_world (rotation, uniform scale,
        translation); the cameras stay rigid (the scale moves the centres, not the axes)."""
        T = np.asarray(source_to_world, dtype=np.float64)
        scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
        R = T[:3, :3] / scale
        moved = []
        for f in self.frames:
            c2w = np.eye(4)
            c2w[:3, :3] = R @ f.camera_to_world[:3, :3]
            c2w[:3, 3] = T[:3, :3] @ f.camera_to_world[:3, 3] + T[:3, 3]
            moved.append(CaptureFrame(f.name, f.image, f.width, f.height, f.K, f.distortion,
                                      f.distortion_params, c2w))
        return Capture(self.format, self.root, tuple(moved), self.problems, "world", self.notes)

    def mean_up(self) -> np.ndarray | None:
        """Unit up vector the cameras agree on, in the capture's coordinates, or None when they do not.

        People hold cameras with little roll but often pitched (looking down at a table), so the cameras'
        right axes (x of OpenCV axes) are horizontal while their up axes are not: up is the direction most
        nearly perpendicular to every right axis (smallest eigenvector of sum x x^T), signed like the mean
        camera up (-y). When the right axes do not pin it down (all alike, e.g. a straight dolly), the mean
        camera up is used if the cameras roughly agree on it (mean of unit vectors at least 0.5 long).
        """
        if not self.frames:
            return None
        right = np.stack([f.camera_to_world[:3, 0] for f in self.frames])
        ups = np.stack([-f.camera_to_world[:3, 1] for f in self.frames])
        mean = ups.mean(axis=0)
        values, vectors = np.linalg.eigh(right.T @ right)
        if values[0] < 0.25 * values[1]:
            up = vectors[:, 0]
            return up if float(up @ mean) >= 0 else -up
        n = float(np.linalg.norm(mean))
        return mean / n if n >= 0.5 else None

    def summary(self, max_problems: int = 20) -> CaptureSummary:
        """JSON-ready summary for job.json, the API and the dashboard."""
        sizes = sorted({(f.width, f.height) for f in self.frames if f.width is not None})
        focal = [float(f.K[0, 0]) for f in self.frames if f.K is not None]
        models = sorted({f.distortion for f in self.frames})
        out: CaptureSummary = {
            "format": self.format,
            "frames": len(self.frames),
            "has_photos": self.has_photos,
            "image_sizes": [list(s) for s in sizes],
            "focal_px": [min(focal), float(np.median(focal)), max(focal)] if focal else None,
            "distortion": models,
            "problems": len(self.problems),
            "problem_messages": list(self.problems[:max_problems]),
            "notes": list(self.notes),
            "up_angle_deg": self.up_angle_deg,
        }
        if self.frames and self.frames[0].K is not None:
            out["K_first"] = np.asarray(self.frames[0].K).tolist()
        return out
