"""Worker test helpers: scenes in the world frame, views, and an independent embree ray caster.

The ray caster is the reference the renderer is checked against: it shares nothing with Blender but the camera
conventions of services.core.camera (K, world_to_camera, pixel centres at u + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from services.core.camera import look_at
from services.worker.passes import NO_FACE, NO_LABEL, ViewGeometry, ViewPasses

# Room labels: class ids per object, instance ids unique per object.
ROOM_CLASSES = {"floor": 1, "wall": 2, "ceiling": 3, "box": 4, "sphere": 5}
SPHERE_RADIUS = 0.3


@dataclass
class Cast:
    """Reference ray cast of one view: per pixel (row-major H x W) triangle id (-1 none), hit point, depths."""

    tri: np.ndarray  # int64 H x W, -1 = none
    loc: np.ndarray  # float64 H x W x 3 world, NaN = none
    z: np.ndarray  # float64 H x W optical-axis depth, NaN = none
    t: np.ndarray  # float64 H x W euclidean distance, NaN = none
    dirs: np.ndarray  # float64 H x W x 3 unit ray directions (world)

    @property
    def hit(self) -> np.ndarray:
        return self.tri >= 0


def raycast(mesh: trimesh.Trimesh, g: ViewGeometry) -> Cast:
    """Cast one ray per pixel centre through K / world_to_camera; first hit only."""
    n = g.resolution
    origins, dirs = g.rays_world()
    tri = np.full(n * n, -1, dtype=np.int64)
    loc = np.full((n * n, 3), np.nan)
    index_tri, index_ray, locations = RayMeshIntersector(mesh).intersects_id(
        origins, dirs, multiple_hits=False, return_locations=True
    )
    tri[index_ray] = index_tri
    loc[index_ray] = locations
    cam = loc @ g.world_to_camera[:3, :3].T + g.world_to_camera[:3, 3]
    t = np.linalg.norm(loc - origins, axis=1)
    return Cast(tri=tri.reshape(n, n), loc=loc.reshape(n, n, 3), z=cam[:, 2].reshape(n, n),
                t=t.reshape(n, n), dirs=dirs.reshape(n, n, 3))


def smooth_mask(cast: Cast, rel: float = 0.02) -> np.ndarray:
    """Pixels whose 8 neighbours also hit, at depths within `rel` of theirs (away from silhouettes/occlusions)."""
    z = np.where(cast.hit, cast.z, np.nan)
    P = np.pad(z, 1, constant_values=np.nan)
    n = z.shape[0]
    ok = cast.hit.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nb = P[1 + dy:1 + dy + n, 1 + dx:1 + dx + n]
            with np.errstate(invalid="ignore"):
                ok &= np.isfinite(nb) & (np.abs(nb - z) < rel * np.nan_to_num(z, nan=0.0))
    return ok


def cast_normals_cam(mesh: trimesh.Trimesh, cast: Cast, g: ViewGeometry) -> np.ndarray:
    """Hit triangles' normals in DESIGN camera axes (x right, y up, z towards viewer), facing the camera."""
    fn = np.asarray(mesh.face_normals)[np.maximum(cast.tri, 0)]
    facing = np.einsum("hwc,hwc->hw", fn, cast.dirs) > 0
    fn = np.where(facing[..., None], -fn, fn)
    n_cv = fn @ g.rotation.T
    return n_cv * np.array([1.0, -1.0, -1.0])


def raycast_passes(mesh: trimesh.Trimesh, g: ViewGeometry, *, face_class: np.ndarray | None = None,
                   face_instance: np.ndarray | None = None, grey: int = 128) -> ViewPasses:
    """A ViewPasses made by ray casting (no Blender): for testing derived cues against known geometry."""
    c = raycast(mesh, g)
    h = c.hit
    fn = np.asarray(mesh.face_normals)[np.maximum(c.tri, 0)]
    facing = np.einsum("hwc,hwc->hw", fn, c.dirs) > 0
    fn = np.where(facing[..., None], -fn, fn)
    p = ViewPasses(
        geometry=g,
        depth_z=np.where(h, c.z, np.inf).astype(np.float32),
        normal_world=np.where(h[..., None], fn, 0.0).astype(np.float32),
        rgb=np.repeat(np.where(h, grey, 0)[..., None], 3, axis=-1).astype(np.uint8),
        face_index=np.where(h, c.tri, int(NO_FACE)).astype(np.uint32),
    )
    if face_class is not None and face_instance is not None:
        p.face_class = np.where(h, face_class[np.maximum(c.tri, 0)], NO_LABEL).astype(np.int32)
        p.face_instance = np.where(h, face_instance[np.maximum(c.tri, 0)], NO_LABEL).astype(np.int32)
    return p


def object_view(mesh: trimesh.Trimesh, direction: np.ndarray, resolution: int, fov_deg: float = 60.0,
                fill: float = 0.8, roll: float = 0.0) -> ViewGeometry:
    """A view looking at the mesh's bounding-box centre from `direction`, framing it to ~`fill` of the image."""
    c = mesh.bounds.mean(axis=0)
    radius = np.linalg.norm(mesh.extents) / 2
    fov = np.radians(fov_deg)
    dist = radius / np.tan(fov / 2) / fill
    d = np.asarray(direction, dtype=np.float64)
    W = look_at(c + d / np.linalg.norm(d) * dist, c, roll_rad=roll)
    return ViewGeometry(W, fov, resolution)


def make_room() -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    """A labelled synthetic room (metres, +Z up): floor, 4 walls, ceiling, two boxes and a sphere.

    Returns the mesh (face colours per object) and per-face class and instance ids.
    """
    parts: list[tuple[trimesh.Trimesh, str, tuple[int, int, int]]] = []

    def quad(corners: np.ndarray) -> trimesh.Trimesh:
        return trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False)

    L, H = 2.0, 2.5  # half-size of the floor, height
    parts.append((quad(np.array([[-L, -L, 0], [L, -L, 0], [L, L, 0], [-L, L, 0]])), "floor", (150, 120, 90)))
    parts.append((quad(np.array([[-L, -L, H], [-L, L, H], [L, L, H], [L, -L, H]])), "ceiling", (230, 230, 230)))
    walls = [([-L, L], [L, L]), ([L, L], [L, -L]), ([L, -L], [-L, -L]), ([-L, -L], [-L, L])]
    for i, (a, b) in enumerate(walls):
        parts.append((quad(np.array([[*a, 0], [*b, 0], [*b, H], [*a, H]])), "wall", (200, 180 - 30 * i, 160)))
    box1 = trimesh.creation.box(extents=[0.6, 0.6, 0.8])
    box1.apply_translation([-0.6, 0.6, 0.4])
    parts.append((box1, "box", (60, 90, 200)))
    box2 = trimesh.creation.box(extents=[0.5, 0.8, 0.5])
    box2.apply_translation([0.7, 0.9, 0.25])
    parts.append((box2, "box", (40, 160, 60)))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_RADIUS)
    sphere.apply_translation([0.1, 0.3, 1.2])
    parts.append((sphere, "sphere", (210, 60, 50)))
    meshes, cls, inst, colours = [], [], [], []
    for i, (m, kind, rgb) in enumerate(parts):
        meshes.append(m)
        cls.append(np.full(len(m.faces), ROOM_CLASSES[kind], dtype=np.int32))
        inst.append(np.full(len(m.faces), i + 1, dtype=np.int32))
        colours.append(np.tile([*rgb, 255], (len(m.faces), 1)))
    vertices, faces, offset = [], [], 0
    for m in meshes:
        vertices.append(m.vertices)
        faces.append(m.faces + offset)
        offset += len(m.vertices)
    room = trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False,
                           face_colors=np.concatenate(colours).astype(np.uint8))
    return room, np.concatenate(cls), np.concatenate(inst)


def room_view(resolution: int) -> ViewGeometry:
    """Inside the room, looking at the boxes and the sphere."""
    return ViewGeometry(look_at(np.array([0.2, -1.7, 1.5]), np.array([0.0, 0.5, 0.7]), roll_rad=0.05),
                        np.radians(75.0), resolution)


@pytest.fixture(scope="session")
def banana_path(scenes_dir: Path) -> Path:
    return scenes_dir / "ycb_banana" / "textured_simple_reoriented.obj"


@pytest.fixture(scope="session")
def bunny_path(scenes_dir: Path) -> Path:
    return scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"
