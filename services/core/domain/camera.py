"""Camera conventions shared by planning and rendering, so a planned pose and a rendered pixel agree.
Pure numpy.

World frame: metres, +Z up (after the space's unit/up-axis normalisation).
OpenCV camera axes: x right, y down, z forward. Blender camera axes: x right, y up, looking down -z.
K = [[f,0,W/2],[0,f,H/2],[0,0,1]], f = (W/2)/tan(fov/2); pixel (u, v) has its centre at (u+0.5, v+0.5).
"""

from __future__ import annotations

import numpy as np

CV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])

CONVENTIONS = {
    "world": "metres, +Z up, the space's frame after unit/up-axis normalisation (see source_to_world)",
    "camera_axes": "OpenCV: x right, y down, z forward (world_to_camera)",
    "K": "[[f,0,W/2],[0,f,H/2],[0,0,1]], f=(W/2)/tan(fov/2), pixel centres at u+0.5, v+0.5",
    "blender_camera": "matrix_world = inverse(world_to_camera) @ diag(1,-1,-1,1)",
    "depth": "uint16, metres * 512 along the optical axis (zbuffer) or to the centre (euclidean); 65535 = "
    "none",
    "normal": "camera space (x right, y up, z towards viewer), px = 255*(0.5-0.5x, 0.5+0.5y, 0.5+0.5z)",
    "fragments": "uint32 face index in trimesh.load(source, force='mesh'), 4294967295 = none",
    "position": "float32 EXR, world XYZ in metres, NaN = none",
}


def focal_px(fov_rad: float, width: int) -> float:
    """Focal length in pixels for a horizontal field of view (radians) and image width (pixels)."""
    return (width / 2.0) / np.tan(fov_rad / 2.0)


def intrinsics(fov_rad: float, width: int, height: int | None = None) -> np.ndarray:
    """3x3 pinhole K in pixels (square pixels, principal point at the image centre)."""
    height = width if height is None else height
    f = focal_px(fov_rad, width)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(position: np.ndarray, target: np.ndarray, roll_rad: float = 0.0,
            up: np.ndarray | None = None) -> np.ndarray:
    """4x4 world_to_camera (OpenCV axes) for a camera at `position` looking at `target`.

    Roll turns the camera about its optical axis, relative to gravity (world +Z): roll 0 keeps the
    image's up direction as close to +Z as possible. Positive roll turns the image clockwise as seen by
    the viewer (camera x towards world-down).
    """
    position = np.asarray(position, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - position
    n = np.linalg.norm(z)
    if n == 0:
        raise ValueError("camera position and target coincide")
    z /= n
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)  # OpenCV x = forward x up (right-handed, y down)
    if np.linalg.norm(x) < 1e-9:  # looking straight up/down: any horizontal right vector will do
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    W = np.eye(4)
    W[:3, :3] = R
    W[:3, 3] = -R @ position
    return W


def camera_center(world_to_camera: np.ndarray) -> np.ndarray:
    """Camera centre in world coordinates."""
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return -R.T @ t


def blender_matrix_world(world_to_camera: np.ndarray) -> np.ndarray:
    """Blender camera object matrix_world from an OpenCV world_to_camera."""
    return np.linalg.inv(world_to_camera) @ CV_TO_BLENDER


def project(points: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project Nx3 world points to pixel coordinates (continuous; centre of pixel u is u+0.5) and depth z."""
    pts = np.asarray(points, dtype=np.float64)
    cam = pts @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam[:, :2] / z[:, None]) @ K[:2, :2].T + K[:2, 2]
    return uv, z


def pixel_rays(
    K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (world) of rays through every pixel centre, row-major (H*W, 3).

    Also usable for depth conversion: the z of a unit ray in camera axes is the cosine to the axis.
    """
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1).reshape(-1, 3)
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    R = world_to_camera[:3, :3]
    d_world = d_cam @ R  # R^T d for each row
    origin = np.broadcast_to(camera_center(world_to_camera), d_world.shape)
    return np.ascontiguousarray(origin), d_world


def rotation_to_quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a 3x3 rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def quaternion_wxyz_to_rotation(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rotation_to_euler_xyz(R: np.ndarray) -> np.ndarray:
    """Blender 'XYZ' Euler angles (radians) of a rotation matrix R = Rz @ Ry @ Rx."""
    sy = -R[2, 0]
    y = np.arcsin(np.clip(sy, -1.0, 1.0))
    if abs(sy) < 1 - 1e-9:
        x = np.arctan2(R[2, 1], R[2, 2])
        z = np.arctan2(R[1, 0], R[0, 0])
    else:  # gimbal lock: fold z into x
        x = np.arctan2(-R[1, 2], R[1, 1])
        z = 0.0
    return np.array([x, y, z])


def euler_xyz_to_rotation(euler: np.ndarray) -> np.ndarray:
    """Rotation matrix Rz @ Ry @ Rx of Blender 'XYZ' Euler angles (radians); inverse of
    rotation_to_euler_xyz."""
    x, y, z = np.asarray(euler, dtype=np.float64)
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def world_to_camera_from_blender(location: np.ndarray, euler_xyz: np.ndarray) -> np.ndarray:
    """OpenCV world_to_camera of a Blender camera given its location and 'XYZ' Euler rotation (Omnidata
    point_info)."""
    matrix_world = np.eye(4)
    matrix_world[:3, :3] = euler_xyz_to_rotation(euler_xyz)
    matrix_world[:3, 3] = np.asarray(location, dtype=np.float64)
    return np.linalg.inv(matrix_world @ CV_TO_BLENDER)
