"""Posed captures: photographs with their cameras, read from the formats capture tools write (COLMAP,
nerfstudio / instant-ngp transforms.json, ScanNet exports, 7-Scenes/3DMatch/BundleFusion, Omnidata
camera_poses.json).

    capture = find_capture(folder)          # None when the folder holds no capture
    world = capture.in_world(space.source_to_world)
"""

from services.core.ingest.capture.detect import FORMATS, find_capture
from services.core.ingest.capture.model import Capture, CaptureError, CaptureFrame

__all__ = ["FORMATS", "Capture", "CaptureError", "CaptureFrame", "find_capture"]
