"""A capture photo seen through another pinhole camera at the same centre: undistortion, resampling and the
rotation homography of fixated views, in one mapping. Pure numpy/scipy.

For each pixel centre of the view (K_view, world_to_camera_view; pixel centres at u + 0.5) the ray is turned
into the photo's camera axes, distorted by the photo's lens and sampled bilinearly from the photo. This is
exact when the two cameras share a centre (any rotation between them); translation between the centres is
parallax and is not handled here (photo-textured views project through the mesh instead). When the view
samples the photo sparser than its pixels, the photo is low-pass filtered first so the view does not alias.
Photos come decoded no larger than the view needs (services.core.ingest.capture.photos), so that filter works
on few pixels.
"""

from __future__ import annotations

import numpy as np

from services.core.ingest.capture.distortion import project_to_photo
from services.core.ingest.capture.model import CaptureFrame
from services.core.ingest.capture.photos import Photo

COVERAGE_MARGIN_PX = 0.5  # a pixel is covered when its bilinear footprint lies inside the photo


def view_rays_cam(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) unnormalised ray directions (x, y, 1) through the pixel centres, OpenCV camera axes."""
    u = (np.arange(width) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(height) + 0.5 - K[1, 2]) / K[1, 1]
    d = np.ones((height, width, 3))
    d[..., 0] = u[None, :]
    d[..., 1] = v[:, None]
    return d


def photo_coords(frame: CaptureFrame, K_view: np.ndarray, world_to_camera_view: np.ndarray, width: int,
                 height: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 2) photo pixel coordinates of each view pixel centre (centre of photo pixel u at u + 0.5), and
    which view pixels the photo covers. Both cameras' rotations must be in the same (world) frame."""
    if frame.K is None or frame.width is None or frame.height is None:
        raise ValueError(f"frame {frame.name} has no intrinsics")
    d_view = view_rays_cam(K_view, width, height).reshape(-1, 3)
    R_view = np.asarray(world_to_camera_view)[:3, :3]
    R_photo = frame.world_to_camera[:3, :3]
    d_photo = d_view @ (R_photo @ R_view.T).T  # view camera -> world -> photo camera
    uv, front = project_to_photo(frame.K, frame.distortion, frame.distortion_params, d_photo)
    m = COVERAGE_MARGIN_PX
    inside = (
        front
        & (uv[:, 0] >= m)
        & (uv[:, 0] <= frame.width - m)
        & (uv[:, 1] >= m)
        & (uv[:, 1] <= frame.height - m)
    )
    return uv.reshape(height, width, 2), inside.reshape(height, width)


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """float32 (..., C) bilinear samples of an H x W x C image at continuous coordinates (centre of u at u +
    0.5), clamped at the border."""
    h, w = image.shape[:2]
    x = np.clip(uv[..., 0] - 0.5, 0.0, w - 1.0)
    y = np.clip(uv[..., 1] - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0)
    fx = (x - x0)[..., None].astype(np.float32)
    fy = (y - y0)[..., None].astype(np.float32)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    def at(yi: np.ndarray, xi: np.ndarray) -> np.ndarray:  # gathered, then float: no float copy of the photo
        return image[yi, xi].astype(np.float32)

    top = at(y0, x0) * (1 - fx) + at(y0, x1) * fx
    bottom = at(y1, x0) * (1 - fx) + at(y1, x1) * fx
    return top * (1 - fy) + bottom * fy


def sample_photo(photo: Photo, uv: np.ndarray) -> np.ndarray:
    """float32 (..., 3) bilinear samples of a photo at the full photo's continuous coordinates `uv`."""
    return sample_bilinear(photo.pixels, uv * photo.scale)


def prefilter(photo: Photo, frame: CaptureFrame, K_view: np.ndarray) -> np.ndarray:
    """The photo's pixels low-pass filtered for a view that samples them `scale` pixels apart (no-op when
    scale <= 1.5)."""
    assert frame.K is not None
    image = photo.pixels
    scale = photo.scale * float(np.sqrt(frame.K[0, 0] * frame.K[1, 1]) / np.sqrt(K_view[0, 0] * K_view[1, 1]))
    if scale <= 1.5:
        return image
    from scipy.ndimage import gaussian_filter

    sigma = 0.45 * scale
    return gaussian_filter(image.astype(np.float32), sigma=(sigma, sigma, 0), mode="nearest")


def photo_for_view(photo: Photo, frame: CaptureFrame, K_view: np.ndarray, world_to_camera_view: np.ndarray,
                   width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(uint8 H x W x 3 rgb, bool H x W coverage) of the photo resampled to the view; 0 where it does not
    reach."""
    uv, covered = photo_coords(frame, K_view, world_to_camera_view, width, height)
    rgb = sample_bilinear(prefilter(photo, frame, K_view), uv * photo.scale)
    rgb = np.where(covered[..., None], np.clip(np.rint(rgb), 0, 255), 0).astype(np.uint8)
    return rgb, covered


def coverage_fraction(
    frame: CaptureFrame, K_view: np.ndarray, world_to_camera_view: np.ndarray, size: int = 16
) -> float:
    """Share of a square view's pixels the frame's photo covers, from a size x size probe (planning)."""
    scale = size / (2.0 * K_view[0, 2])
    K_probe = np.array(
        [[K_view[0, 0] * scale, 0, size / 2.0], [0, K_view[1, 1] * scale, size / 2.0], [0, 0, 1]]
    )
    _, covered = photo_coords(frame, K_probe, world_to_camera_view, size, size)
    return float(covered.mean())
