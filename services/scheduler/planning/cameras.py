"""Camera positions (world metres, +Z up): generated in free space, provided, or on a sphere (objects).

generate: a 3D Poisson-disc sample of the free space inside the scan.
  1. Floors: faces whose normal is within 15 degrees of +Z (the floor rule of core.ingest.frame.gravity),
     grouped by height (a gap > 5 cm starts a new group); groups with >= 20 % of the largest group's area (and
     >= 0.5 m^2) are floors, so each storey of a multi-floor scan counts and table tops or stair steps do not.
  2. Candidates: area-uniform points on the floor faces, raised by a height ~ U[height_min, height_max]
     (or drawn from height_quantiles_m; floors 'lowest' keeps the lowest floor only).
  3. Filters, cheapest first: the vertical segment from the floor point to the camera (plus the
     clearance) is free (so the camera is above *that* floor, under any ceiling); the exact distance to
     the mesh is >= clearance (KD-tree of face centroids, exact point-triangle distances near the
     surface: `MeshQueries.near_mesh`); inside by ray parity (odd number of crossings) in 7 fixed
     directions, majority vote, so a hole in the scan flips only the rays that pass through it. The
     directions lean horizontal and downward because scans often lack ceilings (enclosed false skips it).
  4. Poisson disc: candidates in their (random) order, each kept if no kept camera is within
     min_spacing; stops at max_count. Enough candidates are drawn to nearly saturate the space when
     its capacity is below max_count. With height_quantiles_m the spacing is between the floor points
     (the heights then keep their distribution).
provided: the JobSpec poses (world frame).
object: on a sphere around a single object: centre = bounding-sphere centre, radius =
  object_distance_factor * bounding radius; a Fibonacci lattice turned by a random rotation, each
  direction normalised before scaling so every camera is exactly on the sphere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import sparse
from scipy.spatial import cKDTree

from services.core.domain.camera import quaternion_wxyz_to_rotation
from services.core.domain.jobspec import CameraSpec
from services.core.domain.plan import PlanError
from services.core.ingest.frame.gravity import FLOOR_CONE_COS
from services.scheduler.planning.views import quantile_sample
from services.scheduler.planning.visibility import MeshQueries

FLOOR_GAP_M = 0.05
FLOOR_MIN_FRACTION = 0.2  # of the largest floor group's area: every storey counts, table tops do not
FLOOR_MIN_AREA_M2 = 0.5
MAX_CANDIDATES = 100_000
CANDIDATES_PER_CAMERA = 30


def _parity_directions() -> np.ndarray:
    # five near-horizontal rays at generic azimuths/elevations, one steeply down, one steeply up
    az = np.radians([11.0, 83.0, 157.0, 229.0, 301.0, 37.0, 197.0])
    el = np.radians([7.0, -9.0, 5.0, -6.0, 10.0, -77.0, 71.0])
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


PARITY_DIRECTIONS = _parity_directions()


@dataclass(frozen=True)
class Floor:
    """A horizontal upward surface group: median height (m), area (m^2) and its face indices."""

    z: float
    area: float
    faces: np.ndarray


def detect_floors(mesh: trimesh.Trimesh) -> list[Floor]:
    """Floors of a world-frame mesh (see the module docstring), lowest first."""
    n = mesh.face_normals
    up = np.flatnonzero(n[:, 2] > FLOOR_CONE_COS)
    if len(up) == 0:
        return []
    z = mesh.triangles_center[up, 2]
    order = np.argsort(z, kind="stable")
    up, z = up[order], z[order]
    area = mesh.area_faces[up]
    cuts = np.flatnonzero(np.diff(z) > FLOOR_GAP_M) + 1
    groups = np.split(np.arange(len(up)), cuts)
    areas = np.array([area[g].sum() for g in groups])
    keep = areas >= max(FLOOR_MIN_AREA_M2, FLOOR_MIN_FRACTION * areas.max())
    floors = []
    for g, a, k in zip(groups, areas, keep, strict=True):
        if not k:
            continue
        w = np.cumsum(area[g])
        median = float(z[g][np.searchsorted(w, w[-1] / 2)])
        floors.append(Floor(z=median, area=float(a), faces=up[g]))
    return floors


def _sample_on_faces(
    mesh: trimesh.Trimesh, faces: np.ndarray, n: int, rng: np.random.Generator
) -> np.ndarray:
    """n area-uniform points on the given faces (world metres)."""
    area = mesh.area_faces[faces]
    cdf = np.cumsum(area)
    pick = faces[np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(faces) - 1)]
    tri = mesh.triangles[pick]
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return (1 - s)[:, None] * tri[:, 0] + (s * (1 - r2))[:, None] * tri[:, 1] + (s * r2)[:, None] * tri[:, 2]


def inside_by_parity(q: MeshQueries, points: np.ndarray) -> np.ndarray:
    """(n,) bool: an odd number of crossings in the majority of PARITY_DIRECTIONS."""
    k = len(PARITY_DIRECTIONS)
    o = np.repeat(points, k, axis=0)
    d = np.tile(PARITY_DIRECTIONS, (len(points), 1))
    odd = (q.crossings(o, d) % 2 == 1).reshape(len(points), k)
    return odd.sum(axis=1) * 2 > k


def poisson_select(candidates: np.ndarray, min_spacing: float, max_count: int) -> np.ndarray:
    """Indices of a greedy Poisson-disc subset in candidate order: pairwise distances >= min_spacing."""
    if len(candidates) == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(candidates).query_pairs(min_spacing, output_type="ndarray")
    n = len(candidates)
    if len(pairs):
        both = np.concatenate([pairs, pairs[:, ::-1]])
        adj = sparse.csr_matrix((np.ones(len(both), dtype=bool), (both[:, 0], both[:, 1])), shape=(n, n))
        indptr, indices = adj.indptr, adj.indices
    else:
        indptr, indices = np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    blocked = np.zeros(n, dtype=bool)
    kept: list[int] = []
    for i in range(n):
        if blocked[i]:
            continue
        kept.append(i)
        if len(kept) >= max_count:
            break
        blocked[indices[indptr[i]:indptr[i + 1]]] = True
    return np.array(kept, dtype=np.int64)


def generate_cameras(q: MeshQueries, spec: CameraSpec, rng: np.random.Generator) -> np.ndarray:
    """Poisson-disc camera positions (n, 3) in the free space above the floors (module docstring)."""
    mesh = q.mesh
    floors = detect_floors(mesh)
    if not floors:
        raise PlanError(
            "no floor found (no large upward-facing horizontal surface in the world frame, +Z up): "
            "for a single object use cameras.mode 'object'; for a scan check up_axis and unit_scale"
        )
    if spec.floors == "lowest":
        floors = floors[:1]
    faces = np.concatenate([f.faces for f in floors])
    floor_area = float(sum(f.area for f in floors))
    band = spec.height_max_m - spec.height_min_m
    # random sequential packing of spheres of diameter s jams near 0.73 V / s^3 centres (discs: 0.70 A / s^2)
    capacity = 0.73 * floor_area * band / spec.min_spacing_m**3
    if spec.height_quantiles_m is not None:
        capacity = 0.70 * floor_area / spec.min_spacing_m**2
    wanted = max(1.0, min(float(spec.max_count), capacity))
    n = int(np.clip(CANDIDATES_PER_CAMERA * wanted, 2000, MAX_CANDIDATES))
    base = _sample_on_faces(mesh, faces, n, rng)
    if spec.height_quantiles_m is not None:
        h = quantile_sample(rng, spec.height_quantiles_m, n)
    else:
        h = rng.uniform(spec.height_min_m, spec.height_max_m, n)
    cand = base + h[:, None] * np.array([0.0, 0.0, 1.0])

    lift = 1e-5 * q.scale  # start above the floor face so the ray does not hit it at t = 0
    up_dist, _ = q.first_hit(base + [0.0, 0.0, lift], np.tile([0.0, 0.0, 1.0], (n, 1)))
    ok = up_dist + lift >= h + spec.clearance_m
    idx = np.flatnonzero(ok)
    if spec.clearance_m > 0 and len(idx):
        idx = idx[~q.near_mesh(cand[idx], spec.clearance_m)]
    if len(idx) and spec.enclosed:
        idx = idx[inside_by_parity(q, cand[idx])]
    # with height quantiles the spacing is kept between floor points: a 3D packing of a thin band would favour
    # its sparse heights (blue noise evens out density) and lose the heights' distribution
    spaced = base if spec.height_quantiles_m is not None else cand
    chosen = idx[poisson_select(spaced[idx], spec.min_spacing_m, spec.max_count)]
    return cand[chosen]


def provided_cameras(spec: CameraSpec) -> np.ndarray:
    """Positions (n, 3) of the JobSpec's provided poses, world metres."""
    pos = np.array([p.location for p in spec.poses or []], dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pos).all():
        raise PlanError("cameras.poses: every location must be finite")
    return pos


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random 3x3 rotation (normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    return quaternion_wxyz_to_rotation(q / np.linalg.norm(q))


def object_cameras(
    mesh: trimesh.Trimesh, spec: CameraSpec, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, float]:
    """(positions (n, 3), centre (3,), radius m): a turned Fibonacci lattice exactly on the camera sphere."""
    sphere = mesh.bounding_sphere.primitive
    centre = np.asarray(sphere.center, dtype=np.float64)
    radius = spec.object_distance_factor * float(sphere.radius)
    n = spec.object_count
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    u = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1) @ random_rotation(rng).T
    # normalise after rotating: the original Omnidata code scaled unnormalised vectors, which put
    # cameras off the sphere
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return centre + radius * u, centre, radius
