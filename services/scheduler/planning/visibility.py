"""Geometric queries on a space's mesh for planning: line of sight, first hits, crossings, clearance.

World frame, metres. Every ray query goes through Embree (trimesh's `mesh.ray` backed by embreex)
in vectorised batches; a pure-Python ray loop would make a 5M-ray plan take minutes, so we refuse to
run without Embree instead of silently falling back to trimesh's numpy tracer.

Embree works in float32 on trimesh's rescaled copy of the mesh (about 100 units across), so hit
distances carry a relative error around 1e-7 of the mesh size; line-of-sight tolerances are raised
to at least 1e-5 * mesh.scale (0.25 mm in a 25 m space) to stay clear of that noise.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from services.core.domain.plan import PlanError

RAY_BATCH = 1 << 19  # rays per Embree call: bounds the temporary arrays (~50 MB)
_LEVEL_GROWTH = 4.0  # face-size levels of the distance index
_BALL_CHUNK = 4096
_PAIR_CHUNK = 1 << 20


def require_embree(mesh: trimesh.Trimesh) -> None:
    """Raise PlanError unless `mesh.ray` is trimesh's Embree intersector (embreex installed)."""
    module = type(mesh.ray).__module__
    if not module.endswith("ray_pyembree") or not hasattr(mesh.ray, "_scene"):
        raise PlanError(
            f"planning needs Embree ray casting, but mesh.ray is {module}; install the 'embreex' package"
        )


class MeshQueries:
    """Batched geometric queries on one world-frame mesh; counts the rays it casts."""

    def __init__(self, mesh: trimesh.Trimesh):
        require_embree(mesh)
        self.mesh = mesh
        self.scale = float(mesh.scale)  # bounding-box diagonal, metres
        self._wrap = mesh.ray._scene  # trimesh's cached Embree scene on the rescaled mesh
        self._k = float(self._wrap.scale)  # metres -> Embree units
        self.rays = 0
        self._faces: _FaceIndex | None = None

    # -- rays ------------------------------------------------------------------------------------

    def _run(self, origins: np.ndarray, dirs: np.ndarray, **kw: object) -> object:
        self.rays += len(origins)
        return self._wrap.run(origins, dirs.astype(np.float32), **kw)

    def line_of_sight(self, origins: np.ndarray, targets: np.ndarray, tol: float) -> np.ndarray:
        """(n,) bool: nothing blocks the segment from each origin to within `tol` metres of its target.

        The ray is cast from the origin toward the target; it is clear when its first hit lies
        within the tolerance of the target or beyond it (or there is no hit).
        """
        origins = np.asarray(origins, dtype=np.float64)
        targets = np.asarray(targets, dtype=np.float64)
        out = np.ones(len(origins), dtype=bool)
        tol = max(float(tol), 1e-5 * self.scale)
        for s in range(0, len(origins), RAY_BATCH):
            o, t = origins[s:s + RAY_BATCH], targets[s:s + RAY_BATCH]
            d = t - o
            dist = np.linalg.norm(d, axis=1)
            reach = dist - tol
            live = reach > 0  # a target within the tolerance of the origin is trivially in sight
            if not live.any():
                continue
            dirs = d[live] / dist[live, None]
            occluded = self._run(
                o[live], dirs, dists=(reach[live] * self._k).astype(np.float32), query="OCCLUDED"
            )
            seg = out[s:s + RAY_BATCH]
            seg[np.flatnonzero(live)] = np.asarray(occluded) == -1
        return out

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (metres, inf when none) and face index (-1 when none) of each ray's first hit."""
        origins = np.asarray(origins, dtype=np.float64)
        dirs = np.asarray(dirs, dtype=np.float64)
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        dist = np.full(len(origins), np.inf)
        face = np.full(len(origins), -1, dtype=np.int64)
        for s in range(0, len(origins), RAY_BATCH):
            r = self._run(origins[s:s + RAY_BATCH], dirs[s:s + RAY_BATCH], output=1)
            hit = r["geomID"] != -1  # type: ignore[index]
            d = r["tfar"].astype(np.float64) / self._k  # type: ignore[index]
            dist[s:s + RAY_BATCH][hit] = d[hit]
            face[s:s + RAY_BATCH][hit] = r["primID"][hit]  # type: ignore[index]
        return dist, face

    def crossings(self, origins: np.ndarray, dirs: np.ndarray, max_hits: int = 64) -> np.ndarray:
        """(n,) number of surface crossings along each ray (all hits, not only the first)."""
        o = np.array(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        counts = np.zeros(len(o), dtype=np.int64)
        step = 1e-6 * self.scale  # past the surface just hit, above float32 noise
        live = np.arange(len(o))
        for _ in range(max_hits):
            if len(live) == 0:
                break
            dist, _ = self.first_hit(o[live], d[live])
            hit = np.isfinite(dist)
            live_hit = live[hit]
            counts[live_hit] += 1
            o[live_hit] += d[live_hit] * (dist[hit] + step)[:, None]
            live = live_hit
        return counts

    # -- distances -------------------------------------------------------------------------------

    def near_mesh(self, points: np.ndarray, radius: float) -> np.ndarray:
        """(n,) bool: the exact distance from each point to the mesh is below `radius` metres."""
        if self._faces is None:
            self._faces = _FaceIndex(self.mesh)
        return self._faces.near(np.asarray(points, dtype=np.float64), float(radius))

    def closest_within(self, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact distance (m; inf when the mesh is farther than `radius`) and the closest mesh point
        ((n, 3); the point itself when farther) of each point."""
        if self._faces is None:
            self._faces = _FaceIndex(self.mesh)
        return self._faces.closest(np.asarray(points, dtype=np.float64), float(radius))


class _FaceIndex:
    """Exact point-to-mesh distance tests. Faces are grouped by bounding radius into levels growing 4x
    (one level for an evenly tessellated scan); each level has a KD-tree of face centroids, so only
    faces whose bounding sphere comes within the query radius get an exact point-triangle distance."""

    def __init__(self, mesh: trimesh.Trimesh):
        tris = np.asarray(mesh.triangles, dtype=np.float64)
        centroids = tris.mean(axis=1)
        radii = np.linalg.norm(tris - centroids[:, None, :], axis=2).max(axis=1)
        self.tris, self.centroids, self.radii = tris, centroids, radii
        r0 = max(float(np.median(radii)), 1e-12)
        level = np.maximum(np.floor(np.log(np.maximum(radii, r0) / r0) / np.log(_LEVEL_GROWTH)), 0).astype(
            int
        )
        self.levels: list[tuple[np.ndarray, float, cKDTree]] = []
        for lv in np.unique(level):
            ids = np.flatnonzero(level == lv)
            self.levels.append(
                (
                    ids, float(radii[ids].max()),
                    cKDTree(centroids[ids], balanced_tree=False, compact_nodes=False),
                )
            )

    def _exact_below(self, pts: np.ndarray, faces: np.ndarray, radius: float) -> np.ndarray:
        out = np.zeros(len(pts), dtype=bool)
        for s in range(0, len(pts), _PAIR_CHUNK):
            p, f = pts[s:s + _PAIR_CHUNK], faces[s:s + _PAIR_CHUNK]
            cp = trimesh.triangles.closest_point(self.tris[f], p)  # type: ignore[no-untyped-call]
            out[s:s + _PAIR_CHUNK] = np.linalg.norm(cp - p, axis=1) < radius
        return out

    def closest(self, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        dist = np.full(len(points), np.inf)
        closest = points.copy()
        for ids, rmax, tree in self.levels:
            lists = tree.query_ball_point(points, radius + rmax)
            lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            if not lens.sum():
                continue
            pi = np.repeat(np.arange(len(points)), lens)
            fi = ids[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])]
            cp = trimesh.triangles.closest_point(self.tris[fi], points[pi])  # type: ignore[no-untyped-call]
            d = np.linalg.norm(cp - points[pi], axis=1)
            order = np.lexsort((d, pi))  # per point, its nearest candidate first
            first = order[np.r_[True, pi[order][1:] != pi[order][:-1]]]
            better = (d[first] < radius) & (d[first] < dist[pi[first]])
            dist[pi[first][better]] = d[first][better]
            closest[pi[first][better]] = cp[first][better]
        return dist, closest

    def near(self, points: np.ndarray, radius: float) -> np.ndarray:
        near = np.zeros(len(points), dtype=bool)
        for ids, rmax, tree in self.levels:
            todo = np.flatnonzero(~near)
            if len(todo) == 0:
                break
            reach = radius + rmax
            d_nn, _ = tree.query(points[todo], k=1, distance_upper_bound=reach)
            near[todo[d_nn < radius]] = True  # a centroid closer than the radius: its triangle is too
            amb = todo[(d_nn < reach) & (d_nn >= radius)]
            for s in range(0, len(amb), _BALL_CHUNK):
                chunk = amb[s:s + _BALL_CHUNK]
                lists = tree.query_ball_point(points[chunk], reach)
                lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
                if not lens.sum():
                    continue
                pi = np.repeat(chunk, lens)
                fi = ids[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])]
                keep = np.linalg.norm(points[pi] - self.centroids[fi], axis=1) < radius + self.radii[fi]
                pi, fi = pi[keep], fi[keep]
                hit = self._exact_below(points[pi], fi, radius)
                near[np.unique(pi[hit])] = True
        return near
