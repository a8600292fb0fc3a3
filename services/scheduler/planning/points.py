"""Points of interest: area-uniform surface samples seen by enough cameras (world metres).

A sample is accepted when at least `min_views` cameras have a clear line of sight to it within
`los_tolerance_m` (`MeshQueries.line_of_sight`: the ray from the camera toward the point has no hit
before the point minus the tolerance). Every camera-sample pair is tested, in Embree batches, and the
full set of cameras with line of sight is kept (views and nonfixated use it).

Budget: at most count * max_tries_per_point samples are drawn, in rounds sized by the acceptance
rate observed so far; when the budget runs out the points found so far are returned with a shortfall
message instead of looping forever.

The normal of a point is its face's normal, flipped when most cameras that see the point are behind
the face (one-sided scans with inconsistent winding), so it faces the viewers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from services.core.domain.jobspec import PointSpec
from services.scheduler.planning.visibility import RAY_BATCH, MeshQueries


@dataclass(frozen=True)
class SampledPoints:
    """Accepted points: positions (n, 3), unit normals (n, 3), cameras with line of sight per point."""

    positions: np.ndarray
    normals: np.ndarray
    visible: tuple[np.ndarray, ...]  # sorted camera indices per point
    samples_drawn: int
    requested: int
    shortfall: str | None


def visibility_matrix(q: MeshQueries, cameras: np.ndarray, points: np.ndarray, tol: float) -> np.ndarray:
    """(n_points, n_cameras) bool line of sight, every pair cast in batches of whole point rows."""
    n_p, n_c = len(points), len(cameras)
    out = np.zeros((n_p, n_c), dtype=bool)
    rows = max(1, RAY_BATCH // max(n_c, 1))
    for s in range(0, n_p, rows):
        p = points[s:s + rows]
        origins = np.tile(cameras, (len(p), 1))
        targets = np.repeat(p, n_c, axis=0)
        out[s:s + len(p)] = q.line_of_sight(origins, targets, tol).reshape(len(p), n_c)
    return out


def sample_points(
    q: MeshQueries, cameras: np.ndarray, spec: PointSpec, count: int, rng: np.random.Generator
) -> SampledPoints:
    """Up to `count` points seen by >= spec.min_views cameras, within the try budget (module docstring)."""
    mesh = q.mesh
    budget = count * spec.max_tries_per_point
    pos: list[np.ndarray] = []
    nor: list[np.ndarray] = []
    vis: list[np.ndarray] = []
    accepted = drawn = 0
    rate = 1.0
    while accepted < count and drawn < budget:
        need = count - accepted
        # every sample costs one ray per camera: ask for just a little more than the observed rate needs
        n = int(
            min(
                budget - drawn, max(64, np.ceil(1.05 * need / max(rate, 1.0 / spec.max_tries_per_point)) + 16)
            )
        )
        seed = int(rng.integers(0, 2**63 - 1))
        pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
        drawn += n
        seen = visibility_matrix(q, cameras, pts, spec.los_tolerance_m)
        ok = np.flatnonzero(seen.sum(axis=1) >= spec.min_views)[:need]
        for i in ok:
            cams = np.flatnonzero(seen[i])
            normal = mesh.face_normals[face[i]].astype(np.float64)
            facing = (cameras[cams] - pts[i]) @ normal
            if (facing < 0).sum() > (facing > 0).sum():
                normal = -normal
            pos.append(pts[i])
            nor.append(normal)
            vis.append(cams)
        accepted += len(ok)
        rate = max(accepted / drawn, 1e-9)
    shortfall = None
    if accepted < count:
        shortfall = (
            f"space yields {accepted} of {count} requested points with >= {spec.min_views} views "
            f"({drawn} surface samples tried, budget {spec.max_tries_per_point} per point)"
        )
    return SampledPoints(
        positions=np.array(pos, dtype=np.float64).reshape(-1, 3),
        normals=np.array(nor, dtype=np.float64).reshape(-1, 3),
        visible=tuple(vis),
        samples_drawn=drawn,
        requested=count,
        shortfall=shortfall,
    )
