"""Lens models of the capture formats, on normalised image coordinates (x/z, y/z of OpenCV camera axes).

`distort` maps an ideal pinhole direction to where the lens puts it (what the photo shows); `undistort`
inverts it by fixed-point iteration (used to synthesise photos and to check the forward model).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _opencv_params(params: Sequence[float]) -> tuple[float, float, float, float, float]:
    k1, k2, p1, p2, k3 = (list(params) + [0.0] * 5)[:5]
    return k1, k2, p1, p2, k3


def distort(model: str, params: Sequence[float], xy: np.ndarray) -> np.ndarray:
    """Distorted normalised coordinates (N, 2) of ideal ones (N, 2) under `model` (see capture.model)."""
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    if model == "none":
        return xy.copy()
    if model == "radial":
        k1, k2 = (list(params) + [0.0, 0.0])[:2]
        r2 = x * x + y * y
        f = 1.0 + k1 * r2 + k2 * r2 * r2
        return np.stack([x * f, y * f], axis=-1)
    if model == "opencv":
        k1, k2, p1, p2, k3 = _opencv_params(params)
        r2 = x * x + y * y
        f = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * f + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * f + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)
    if model == "fisheye":
        k1, k2, k3, k4 = (list(params) + [0.0] * 4)[:4]
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(r > 1e-12, theta_d / r, 1.0)
        return np.stack([x * s, y * s], axis=-1)
    raise ValueError(f"unknown distortion model {model!r}")


def undistort(model: str, params: Sequence[float], xy_d: np.ndarray, iterations: int = 30) -> np.ndarray:
    """Ideal normalised coordinates whose distortion is `xy_d` (N, 2), by fixed-point iteration."""
    xy_d = np.asarray(xy_d, dtype=np.float64)
    if model == "none":
        return xy_d.copy()
    xy = xy_d.copy()
    for _ in range(iterations):
        xy = xy + (xy_d - distort(model, params, xy))
    return xy


def project_to_photo(
    K: np.ndarray, model: str, params: Sequence[float], cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Photo pixel coordinates (N, 2; centre of pixel u at u + 0.5) of points (N, 3) in OpenCV camera axes,
    and which are in front of the camera."""
    cam = np.asarray(cam, dtype=np.float64)
    z = cam[..., 2]
    front = z > 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        xy = cam[..., :2] / np.where(front, z, 1.0)[..., None]
    xy_d = distort(model, params, xy)
    uv = xy_d @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]
    return uv, front
