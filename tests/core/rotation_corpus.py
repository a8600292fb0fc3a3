"""The ingest corpus: real and synthetic rooms in random orientations and units, with their true up and scale.

Shared by tests/core/test_gravity.py (a small, fast draw) and bench/ingest.py (the full figures). Every
case is a source-frame mesh: the room in metres with +Z up (or its stored up), rotated by a random
rotation and expressed in one of the units, so the truth is known exactly.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from tests.scheduler import scenes

# metres per source unit of the exports: millimetres, centimetres, inches, metres
SCALES = (0.001, 0.01, 0.0254, 1.0)


@dataclass(frozen=True)
class Room:
    """A room mesh (metres) and its up direction in that mesh's frame."""

    name: str
    mesh: trimesh.Trimesh
    up: np.ndarray


@dataclass(frozen=True)
class Case:
    """One source mesh to ingest and its truth."""

    room: str
    kind: str  # random | axis
    mesh: trimesh.Trimesh  # source frame, source units
    up: np.ndarray  # true up, source frame
    scale: float  # true metres per source unit


def _open_box(size: np.ndarray, centre_xy: np.ndarray, z0: float, keep_bottom: bool = False) -> trimesh.Trimesh:
    """A furniture box standing at height z0, outward normals, no bottom face (never scanned from below)."""
    box = trimesh.creation.box(extents=size)
    box.apply_translation([centre_xy[0], centre_xy[1], z0 + size[2] / 2])
    if not keep_bottom:
        box.update_faces(box.face_normals[:, 2] > -0.5)
    return box


def synthetic_room(rng: np.random.Generator, name: str, noise_m: float = 0.01, ceiling_missing_p: float = 0.6) -> Room:
    """A furnished room like a reconstruction: random size, ceiling often missing, holes in walls, furniture
    at random angles, vertices jittered by `noise_m` (metres, standard deviation)."""
    size = np.array([rng.uniform(3.0, 8.0), rng.uniform(3.0, 7.0), rng.uniform(2.4, 3.2)])
    room = scenes.box_room(size=tuple(size))
    normals = room.face_normals
    keep = np.ones(len(room.faces), dtype=bool)
    if rng.random() < ceiling_missing_p:  # reconstructions rarely see the ceiling
        keep &= ~(normals[:, 2] < -0.9)
    wall = (np.abs(normals[:, 2]) < 0.1) & (rng.random(len(keep)) < 0.3)  # a missing wall triangle (window, door)
    keep &= ~wall
    room.update_faces(keep)
    parts = [room.subdivide().subdivide()]
    for _ in range(int(rng.integers(3, 8))):
        fsize = np.array([rng.uniform(0.4, 2.0), rng.uniform(0.4, 1.6), rng.uniform(0.4, 2.0)])
        fsize[:2] = np.minimum(fsize[:2], size[:2] / 2)
        xy = rng.uniform(fsize[:2] / 2 + 0.05, size[:2] - fsize[:2] / 2 - 0.05)
        box = _open_box(fsize, np.zeros(2), 0.0)
        box.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1]))
        box.apply_translation([xy[0], xy[1], 0.0])  # furniture is not aligned with the walls
        parts.append(box.subdivide())
    for _ in range(int(rng.integers(1, 3))):  # tables: tops without bottoms
        parts.append(scenes.table(center_xy=tuple(rng.uniform([1, 1], size[:2] - 1)), height=rng.uniform(0.45, 0.9)))
    mesh = trimesh.util.concatenate(parts)
    if noise_m > 0:  # reconstruction noise
        mesh = trimesh.Trimesh(mesh.vertices + rng.normal(0.0, noise_m, mesh.vertices.shape), mesh.faces, process=False)
    return Room(name, mesh, np.array([0.0, 0.0, 1.0]))


def icl_room(scenes_dir: Path, faces: int | None = None) -> Room:
    """The ICL-NUIM living room (stored with -Y up), optionally decimated to about `faces` (fast tests)."""
    mesh = trimesh.load(scenes_dir / "icl_livingroom" / "livingroom.obj", force="mesh")
    if faces is not None and faces < len(mesh.faces):
        import pymeshlab

        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(mesh.vertices, mesh.faces))
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=faces, planarquadric=True, preservenormal=True)
        out = ms.current_mesh()
        mesh = trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=False)
    return Room("icl_livingroom", mesh, np.array([0.0, -1.0, 0.0]))


def axis_rotations() -> list[np.ndarray]:
    """The 24 rotations that map axes onto axes (exact integer matrices)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def _case(room: Room, kind: str, R: np.ndarray, scale: float) -> Case:
    T = np.eye(4)
    T[:3, :3] = R / scale  # metres -> source units, then the source's orientation
    mesh = room.mesh.copy()
    mesh.apply_transform(T)
    return Case(room.name, kind, mesh, R @ room.up, scale)


def cases(rooms: list[Room], n_random: int, seed: int = 0) -> list[Case]:
    """Per room: `n_random` uniformly random rotations and the 24 axis-aligned ones, cycling through SCALES."""
    rng = np.random.default_rng(seed)
    out = []
    for room in rooms:
        rotations = [("random", R) for R in Rotation.random(n_random, random_state=rng).as_matrix()]
        rotations += [("axis", R) for R in axis_rotations()]
        for i, (kind, R) in enumerate(rotations):
            out.append(_case(room, kind, R, SCALES[i % len(SCALES)]))
    return out


def up_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Angle between two directions, degrees."""
    c = float(np.dot(estimate, truth) / (np.linalg.norm(estimate) * np.linalg.norm(truth)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
