"""The pass set of one rendered view (the internal `passes` cue) and the view geometry it was rendered with.

Frames and units (services/core/domain/camera.py, the conventions planning and rendering share):
- world: metres, +Z up; `world_to_camera` takes world points to OpenCV camera axes (x right, y down, z
  forward);
- pixel (u, v) has its centre at (u + 0.5, v + 0.5); K = [[f,0,W/2],[0,f,H/2],[0,0,1]], f = (W/2)/tan(fov/2).

Arrays are row-major H x W (row 0 = top of the image). "No surface" is marked per array: depth_z = inf,
normal_world = 0, rgb = 0, face_index = 4294967295, labels = -1, curvature = NaN.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from services.core.domain.camera import camera_center, intrinsics, pixel_rays
from services.core.domain.cues import FRAGMENT_NONE

NO_FACE = np.uint32(FRAGMENT_NONE)
NO_LABEL = -1

# Passes read back from a render only when a requested cue needs them (colour and depth always are): normals
# (derived from the face index), the face index, the class/instance ids (labelled spaces; looked up from the
# face index) and the curvature AOVs (whose per-vertex curvature is then not computed either).
RENDER_PASSES: frozenset[str] = frozenset({"normal", "faces", "labels", "curvature"})


class ViewPose(Protocol):
    """What a view context reads of a view: a PlannedView or a ViewGeometry (read-only attributes)."""

    @property
    def world_to_camera(self) -> np.ndarray: ...
    @property
    def fov(self) -> float: ...
    @property
    def resolution(self) -> int: ...


@dataclass(frozen=True)
class ViewGeometry:
    """Pose and intrinsics of one view: OpenCV world_to_camera (4x4, metres), horizontal fov (radians), square
    size."""

    world_to_camera: np.ndarray
    fov: float
    resolution: int

    @classmethod
    def of(cls, view: ViewPose) -> ViewGeometry:
        """Accept a ViewGeometry, or anything with `world_to_camera`, `fov` (rad) and `resolution` (a
        PlannedView)."""
        if isinstance(view, ViewGeometry):
            return view
        W = np.asarray(view.world_to_camera, dtype=np.float64).reshape(4, 4)
        return cls(world_to_camera=W, fov=float(view.fov), resolution=int(view.resolution))

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsics in pixels."""
        return intrinsics(self.fov, self.resolution, self.resolution)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (metres)."""
        return camera_center(self.world_to_camera)

    @property
    def rotation(self) -> np.ndarray:
        """3x3 world-to-OpenCV-camera rotation (rows are the camera axes in world coordinates)."""
        return self.world_to_camera[:3, :3]

    def ray_directions_cam(self) -> np.ndarray:
        """Unit ray directions through every pixel centre in OpenCV camera axes, H x W x 3 (float64)."""
        n = self.resolution
        K = self.K
        centres = np.arange(n) + 0.5
        x = ((centres - K[0, 2]) / K[0, 0])[None, :]
        y = ((centres - K[1, 2]) / K[1, 1])[:, None]
        # (x, y, 1) / its norm, from a row and a column (5x faster than a meshgrid; the same sums in the same
        # order).
        norm = np.sqrt(x * x + y * y + 1.0)
        d = np.empty((n, n, 3))
        d[..., 0], d[..., 1], d[..., 2] = x / norm, y / norm, 1.0 / norm
        return d

    def rays_world(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions (world, (H*W) x 3, row-major) of the pixel-centre rays."""
        return pixel_rays(self.K, self.world_to_camera, self.resolution, self.resolution)


OPTIONAL_ARRAYS = ("normal_world", "face_index", "face_class", "face_instance", "curvature", "photo_coverage")


@dataclass
class ViewPasses:
    """Every per-pixel quantity one Cycles render gives for a view (see the module docstring for 'none'
    markers).

    depth_z: float32 H x W, metres along the optical axis (Cycles' Z pass is planar z), inf = no surface.
    normal_world: float32 H x W x 3, unit geometric normal of the seen triangle in world axes, turned to face
        the camera (as Cycles turns back-facing hits; derived from the face index, not rendered); 0 = no
        surface. None when not asked for (pass "normal").
    rgb: uint8 H x W x 3, unlit sRGB colour (texture / vertex colour / constant grey), 0 = no surface.
    face_index: uint32 H x W, index of the seen triangle in the space's mesh, 4294967295 = no surface. None
    when
        not read back (pass "faces").
    face_class, face_instance: int32 H x W or None (unlabelled space): the space's ids as given (a scan may
    use
        negative ids for unlabelled faces), -1 where nothing is seen (tell the two apart with `hit`).
    curvature: float32 H x W x 2 (k1 >= k2, 1/m, positive = convex) or None when not rendered; NaN = no
    surface. photo_coverage: bool H x W where rgb is a photograph's (services.worker.inputs.photos), None for
    mesh rgb.
    """

    geometry: ViewGeometry
    depth_z: np.ndarray
    normal_world: np.ndarray | None
    rgb: np.ndarray
    face_index: np.ndarray | None
    face_class: np.ndarray | None = None
    face_instance: np.ndarray | None = None
    curvature: np.ndarray | None = None
    # bool H x W: rgb came from a photo here (capture views); else None
    photo_coverage: np.ndarray | None = None
    meta: dict[str, float] = field(default_factory=dict)  # render timings etc., not part of the contract

    @property
    def hit(self) -> np.ndarray:
        """bool H x W: a surface was seen (depth is inf exactly where no face is, so either pass tells)."""
        if self.face_index is not None:
            return self.face_index != NO_FACE
        return np.isfinite(self.depth_z)

    def require(self, name: str) -> np.ndarray:
        """The array `name` (normal_world, face_index, face_class, ...), or a clear error when it was not
        rendered."""
        value = getattr(self, name)
        if value is None:
            raise RuntimeError(
                f"this view's pass set has no {name} (not read back: the cues asked of the render "
                "did not need it)"
            )
        return value

    def position_world(self) -> np.ndarray:
        """float32 H x W x 3 world position (metres) of the seen surface, NaN = none; from depth and pose."""
        g = self.geometry
        d_cam = g.ray_directions_cam()
        t = self.depth_z.astype(np.float64) / d_cam[..., 2]  # euclidean distance along the unit ray
        d_world = d_cam @ g.rotation  # R^T d per pixel
        p = g.center + d_world * t[..., None]
        p[~self.hit] = np.nan
        return p.astype(np.float32)

    def to_bytes(self) -> bytes:
        """Serialise as an uncompressed .npz (fast; this is a worker-side cache, not a dataset file)."""
        arrays: dict[str, np.ndarray] = {
            "world_to_camera": self.geometry.world_to_camera,
            "fov": np.asarray(self.geometry.fov, dtype=np.float64),
            "resolution": np.asarray(self.geometry.resolution, dtype=np.int64),
            "depth_z": self.depth_z,
            "rgb": self.rgb,
        }
        for name in OPTIONAL_ARRAYS:
            value = getattr(self, name)
            if value is not None:
                arrays[name] = value
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> ViewPasses:
        """Inverse of to_bytes."""
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            geometry = ViewGeometry(
                world_to_camera=z["world_to_camera"], fov=float(z["fov"]), resolution=int(z["resolution"])
            )
            opt = {n: z[n] for n in OPTIONAL_ARRAYS if n in z.files}
            return cls(geometry=geometry, depth_z=z["depth_z"], rgb=z["rgb"],
                       **{"normal_world": None, "face_index": None, **opt})
