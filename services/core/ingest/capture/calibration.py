"""A correction of a capture's colour camera, the same for every frame: what alignment refinement finds.

Many RGB-D captures record the depth camera's poses and intrinsics while the photos come from a colour camera
a few centimetres away with another focal length (7-Scenes, Kinect v1). The correction is a focal-length
scale, a principal-point shift (pixels) and the colour camera's offset from the recorded camera (metres, in
the recorded camera's OpenCV axes: x right, y down, z forward). Rotation is left alone: a small rotation and a
principal-point shift move the image alike.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from services.core.domain.capture_records import ColourCorrectionRecord
from services.core.ingest.capture.model import Capture, CaptureFrame


@dataclass(frozen=True)
class ColourCorrection:
    """focal_scale x fx, fy; principal point + (dcx, dcy) px; camera centre moved by offset_m (camera
    axes)."""

    focal_scale: float = 1.0
    dcx: float = 0.0
    dcy: float = 0.0
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def as_dict(self) -> ColourCorrectionRecord:
        """JSON-ready (the plan's record, which the workers apply again)."""
        return {
            "focal_scale": self.focal_scale, "dcx": self.dcx, "dcy": self.dcy,
            "offset_m": list(self.offset_m),
        }

    @classmethod
    def from_dict(cls, d: ColourCorrectionRecord) -> ColourCorrection:
        """Inverse of as_dict."""
        return cls(float(d["focal_scale"]), float(d["dcx"]), float(d["dcy"]),
                   tuple(float(x) for x in d["offset_m"]))  # type: ignore[arg-type]

    def frame(self, f: CaptureFrame) -> CaptureFrame:
        """The frame as the corrected camera sees it (same photo)."""
        K = None
        if f.K is not None:
            K = np.array(f.K, dtype=np.float64)
            K[0, 0] *= self.focal_scale
            K[1, 1] *= self.focal_scale
            K[0, 2] += self.dcx
            K[1, 2] += self.dcy
        move = np.eye(4)
        move[:3, 3] = self.offset_m
        return CaptureFrame(f.name, f.image, f.width, f.height, K, f.distortion, f.distortion_params,
                            f.camera_to_world @ move)

    def capture(self, capture: Capture) -> Capture:
        """Every frame corrected."""
        return replace(capture, frames=tuple(self.frame(f) for f in capture.frames))
