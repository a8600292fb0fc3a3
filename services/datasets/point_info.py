"""A stored view's point_info read back: the keys read and the camera they give."""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from services.core.domain.camera import intrinsics, world_to_camera_from_blender


class StoredPointInfo(TypedDict, total=False):
    """The point_info keys read back here: ours carry K and world_to_camera; the released Omnidata components
    only the field of view, resolution and Blender camera."""

    K: list[list[float]]
    world_to_camera: list[list[float]]
    resolution: int
    field_of_view_rads: float
    camera_location: list[float]
    camera_rotation_final: list[float]
    point_location: list[float]
    camera_distance: float


def camera_of(point_info: StoredPointInfo) -> tuple[np.ndarray, np.ndarray]:
    """K (3x3, pixels) and world_to_camera (4x4, OpenCV axes) of a point_info, float32.

    Our point_info carries both; the released Omnidata components only have the field of view, resolution and
    Blender camera location and Euler rotation, from which the same matrices follow
    (services.core.domain.camera).
    """
    if "K" in point_info and "world_to_camera" in point_info:
        return (
            np.asarray(point_info["K"], np.float32), np.asarray(point_info["world_to_camera"], np.float32),
        )
    res = int(point_info["resolution"])
    K = intrinsics(float(point_info["field_of_view_rads"]), res)
    w2c = world_to_camera_from_blender(np.asarray(point_info["camera_location"]),
                                       np.asarray(point_info["camera_rotation_final"]))
    return K.astype(np.float32), w2c.astype(np.float32)
