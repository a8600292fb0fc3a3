"""The plan-stage cues, made from a SpacePlan alone: point_info, nonfixated and vanishing_points.

The one implementation: `omnidata plan` writes them with `encode_json`, and the worker's cue modules
(services.worker.cues.plan_cues) only register them with the executor. Pixel coordinates are continuous with
the centre of pixel u at u + 0.5; depths and positions are world metres.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import NotRequired, TypedDict

import numpy as np

from services.core.domain.camera import (
    CONVENTIONS,
    blender_matrix_world,
    camera_center,
    project,
    rotation_to_euler_xyz,
    rotation_to_quaternion_wxyz,
)
from services.core.domain.json_types import JSONValue
from services.core.domain.plan import PlannedView, SpacePlan, plan_index


def points_in_view(plan: SpacePlan, view: PlannedView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Other points visible in a view: (point indices, (n, 2) pixel coordinates, (n,) depth along z, metres).

    Visible = the view's camera has line of sight to the point (recorded when the point was accepted)
    and the point projects inside the image in front of the camera. Trajectory frames use the line of
    sight of their nearest camera (an approximation between cameras).
    """
    ix = plan_index(plan)
    cand = ix.points_seen_by.get(view.camera_idx, np.zeros(0, dtype=np.int64))
    cand = cand[cand != view.point_idx]
    if len(cand) == 0:
        return cand, np.zeros((0, 2)), np.zeros(0)
    uv, z = project(ix.positions[cand], view.K, view.world_to_camera)
    res = view.resolution
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < res) & (uv[:, 1] >= 0) & (uv[:, 1] < res)
    return cand[ok], uv[ok], z[ok]


class PointInfo(TypedDict):
    """The point_info JSON of one view: Omnidata's keys, then ours (K, world_to_camera, conventions, ...)."""

    point_uuid: str
    view_id: int
    camera_uuid: str
    camera_location: list[float]
    camera_rotation_final: list[float]
    camera_rotation_final_quaternion: list[float]
    field_of_view_rads: float
    resolution: int
    point_location: list[float]
    point_normal: list[float]
    obliqueness_angle: float
    camera_distance: float
    nonfixated_points_in_view: list[int]
    K: list[list[float]]
    world_to_camera: list[list[float]]
    conventions: dict[str, str]
    space: str
    point_idx: int
    camera_idx: int
    roll_rads: float
    in_sight: bool
    alignment_score: NotRequired[float]
    photo_coverage: NotRequired[float]


class NonfixatedPoint(TypedDict):
    point_idx: int
    point_uuid: str
    pixel: list[float]
    depth_zbuffer_m: float


class NonfixatedView(TypedDict):
    view_id: int
    camera_uuid: str
    camera_location: list[float]
    points: list[NonfixatedPoint]


class Nonfixated(TypedDict):
    """The nonfixated JSON of a point (one file per point)."""

    point_uuid: str
    point_idx: int
    point_location: list[float]
    space: str
    views: list[NonfixatedView]
    conventions: dict[str, str]


class VanishingPoint(TypedDict):
    image: list[float] | None  # pixels; None: at infinity
    direction: list[float]
    gaussian_sphere: list[float]


class VanishingPoints(TypedDict):
    """Vanishing points of the world X, Y, Z axes in one view."""

    x: VanishingPoint
    y: VanishingPoint
    z: VanishingPoint
    conventions: dict[str, str]


def _floats(a: np.ndarray) -> list[float]:
    return np.asarray(a, dtype=np.float64).tolist()


def _matrix(a: np.ndarray) -> list[list[float]]:
    return np.asarray(a, dtype=np.float64).tolist()


def point_info(plan: SpacePlan, view: PlannedView) -> PointInfo:
    """The point_info JSON of one view: Omnidata's keys plus K, world_to_camera and conventions.

    camera_rotation_final is the Blender XYZ Euler (radians) of the Blender camera object
    (looking down its -z, y up); the quaternion is wxyz of the same rotation.
    """
    point = plan.points[view.point_idx]
    camera = plan.cameras[view.camera_idx]
    W = view.world_to_camera
    centre = camera_center(W)
    R_blender = blender_matrix_world(W)[:3, :3]
    others, _, _ = points_in_view(plan, view)
    info: PointInfo = {
        "point_uuid": point.uuid,
        "view_id": int(view.v),
        "camera_uuid": camera.uuid,
        "camera_location": _floats(centre),
        "camera_rotation_final": _floats(rotation_to_euler_xyz(R_blender)),
        "camera_rotation_final_quaternion": _floats(rotation_to_quaternion_wxyz(R_blender)),
        "field_of_view_rads": float(view.fov),
        "resolution": int(view.resolution),
        "point_location": _floats(point.position),
        "point_normal": _floats(point.normal),
        "obliqueness_angle": float(view.obliqueness),
        "camera_distance": float(np.linalg.norm(centre - point.position)),
        "nonfixated_points_in_view": [int(i) for i in others],
        # ours
        "K": _matrix(view.K),
        "world_to_camera": _matrix(W),
        "conventions": dict(CONVENTIONS),
        "space": plan.space_name,
        "point_idx": int(view.point_idx),
        "camera_idx": int(view.camera_idx),
        "roll_rads": float(view.roll),
        "in_sight": bool(view.in_sight),
    }
    if view.alignment is not None:
        info["alignment_score"] = view.alignment
    if view.photo_coverage is not None:
        info["photo_coverage"] = view.photo_coverage
    return info


def nonfixated(plan: SpacePlan, point_idx: int) -> Nonfixated:
    """The nonfixated JSON of a point: for each of its views, the pixels of the other points visible in it."""
    point = plan.points[point_idx]
    views: list[NonfixatedView] = []
    for view in plan.views_of(point_idx):
        idxs, uv, z = points_in_view(plan, view)
        views.append({
            "view_id": int(view.v),
            "camera_uuid": plan.cameras[view.camera_idx].uuid,
            "camera_location": _floats(view.position),
            "points": [
                {
                    "point_idx": int(i),
                    "point_uuid": plan.points[int(i)].uuid,
                    "pixel": _floats(uv[k]),
                    "depth_zbuffer_m": float(z[k]),
                }
                for k, i in enumerate(idxs)
            ],
        })
    return {
        "point_uuid": point.uuid,
        "point_idx": int(point_idx),
        "point_location": _floats(point.position),
        "space": plan.space_name,
        "views": views,
        "conventions": {
            "pixel": "continuous (u, v); the centre of pixel u is at u + 0.5; origin top-left",
            "visibility": "line of sight from the view's camera (trajectory frames: nearest camera) "
                          "and inside the image, in front of the camera",
        },
    }


def vanishing_points(info: Mapping[str, object]) -> VanishingPoints:
    """Vanishing points of the world X, Y, Z axes for a point_info dict.

    `image`: pixel coordinates (continuous, centre of pixel u at u + 0.5), or None when the axis is
    parallel to the image plane (vanishing point at infinity). `direction`: the world axis in OpenCV
    camera axes (unit). `gaussian_sphere`: the same line's unit vector on the Gaussian sphere, signed
    to point in front of the camera (z >= 0), whose central projection is the image vanishing point.
    """
    K = np.asarray(info["K"], dtype=np.float64)
    W = np.asarray(info["world_to_camera"], dtype=np.float64)
    R = W[:3, :3]
    def axis(k: int) -> VanishingPoint:
        d = R[:, k] / np.linalg.norm(R[:, k])
        image: list[float] | None = None
        if abs(d[2]) > 1e-12:
            image = _floats(K[:2, :2] @ (d[:2] / d[2]) + K[:2, 2])
        g = d if d[2] >= 0 else -d
        return {"image": image, "direction": _floats(d), "gaussian_sphere": _floats(g)}

    return {
        "x": axis(0),
        "y": axis(1),
        "z": axis(2),
        "conventions": {
            "image": "pixels, centre of pixel u at u + 0.5; null = at infinity (axis parallel to the image)",
            "direction": "world axis in OpenCV camera axes (x right, y down, z forward)",
            "gaussian_sphere": "unit vector of the axis' line through the camera centre, z >= 0",
        },
    }


def _json_default(o: object) -> JSONValue:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, tuple | set | frozenset):
        return sorted(o) if isinstance(o, set | frozenset) else list(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def encode_json(obj: object) -> bytes:
    """A JSON cue file's bytes, the same from `omnidata plan` and the workers: sorted keys, compact, numpy
    scalars/arrays as plain numbers/lists, UTF-8."""
    # Compact separators keep json's C encoder (indent forces the pure-Python one): 4x faster, 40% smaller
    # files on the multi-megabyte nonfixated JSON of a room.
    return json.dumps(obj, sort_keys=True, default=_json_default, separators=(",", ":")).encode("utf-8")
