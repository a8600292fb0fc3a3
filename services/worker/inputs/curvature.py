"""Per-vertex principal curvatures of a mesh by weighted quadric fitting on a metric neighbourhood. Pure
numpy/scipy.

Why not pymeshlab's APSS (what the Omnidata annotator used): APSS' filter scale is a multiple of the local
point spacing, so the curvature it reports depends on how densely the scan was tessellated; the JobSpec asks
for a neighbourhood radius in metres (`curvature_radius_m`), which a quadric fit honours directly and which is
vectorised here (no per-vertex Python). The estimator:

1. sample the surface uniformly (area-weighted, fixed seed) at a spacing of radius/4, so every neighbourhood
   holds ~50 samples whatever the tessellation (at most MAX_SAMPLES; meshes with more vertices add their
   vertices);
2. for each vertex, take its MAX_NEIGHBOURS nearest samples within the radius (found in a grid of radius-wide
   cells; where balls hold far more, in a k-d tree, which stops at the nearest), Gaussian-weighted by distance
   (sigma = radius/2), dropping samples whose normal points away (> ~70 deg) so thin walls do not mix sides;
3. express them in the vertex's tangent frame (u, v along the surface, h along the vertex normal) and fit
   h = a u^2 + b uv + c v^2 + d u + e v + g by weighted least squares;
4. principal curvatures = eigenvalues of the Monge patch's shape operator I^-1 II at the origin (gradient
   terms d, e included, so a tilted vertex normal does not bias the result).

Units: 1/m when the mesh is in metres. Sign: positive = convex, i.e. the surface bends away from the side its
normals point to (a sphere with outward normals has k1 = k2 = +1/r, a cylinder k1 = 1/r, k2 = 0).
Order: k1 >= k2. Vertices with too few neighbours (< 8) get 0 (flat).
"""

from __future__ import annotations

import numpy as np
import trimesh
from numba import njit
from scipy.spatial import cKDTree

MAX_SAMPLES = 4_000_000  # ~200 MB of samples; beyond it (huge area, tiny radius) neighbourhoods thin out
MIN_SAMPLES = 2_000
MAX_NEIGHBOURS = 96  # > the ~50 samples a full ball holds, so the cap does not shrink the radius
SAMPLES_PER_RADIUS = 4.0
# samples expected in a ball (the sampling alone gives ~50) up to which a grid searches
GRID_MAX_BALL = MAX_NEIGHBOURS
CHUNK = 16_384  # vertices per batch: bounds memory at CHUNK * MAX_NEIGHBOURS * 6 floats
_SEED = 0  # fixed: the same mesh gives the same curvature in every worker


def principal_curvatures(mesh: trimesh.Trimesh, radius: float) -> np.ndarray:
    """Per-vertex (k1, k2), float32 V x 2, in 1/(mesh unit); see the module docstring for the estimator."""
    if radius <= 0:
        raise ValueError(f"curvature radius must be positive, got {radius}")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    if len(verts) == 0 or len(mesh.faces) == 0:
        return np.zeros((len(verts), 2), dtype=np.float32)
    vnormals = np.array(mesh.vertex_normals, dtype=np.float64)
    # Unreferenced or degenerate vertices have no normal: give them one so the batch stays finite.
    bad = ~(np.linalg.norm(vnormals, axis=1) > 0.5)
    vnormals[bad] = [0.0, 0.0, 1.0]
    spacing = radius / SAMPLES_PER_RADIUS
    n_samples = int(np.clip(mesh.area / spacing**2, MIN_SAMPLES, MAX_SAMPLES))
    rng = np.random.default_rng(_SEED)
    pts, fidx = _sample_surface(mesh, n_samples, rng)
    snormals = np.asarray(mesh.face_normals, dtype=np.float64)[fidx]
    if len(verts) > n_samples:  # dense meshes: their own vertices are the better samples
        pts = np.concatenate([pts, verts])
        snormals = np.concatenate([snormals, vnormals])
    t1, t2 = _tangent_frames(vnormals)
    k = min(MAX_NEIGHBOURS, len(pts))
    if len(pts) / max(mesh.area, 1e-300) * np.pi * radius**2 <= GRID_MAX_BALL:
        grid = _SampleGrid(pts, verts, radius)
        return _fit_in_grid(
            verts, vnormals, t1, t2, pts[grid.order], snormals[grid.order], grid.keys, grid.lo, grid.cell,
            grid.dims, float(radius), k,
        )
    # Crowded balls (a dense mesh's own vertices): a k-d tree finds the k nearest without visiting the rest.
    tree = cKDTree(pts)
    out = np.zeros((len(verts), 2), dtype=np.float32)
    for s in range(0, len(verts), CHUNK):
        sl = slice(s, min(s + CHUNK, len(verts)))
        dist, idx = tree.query(verts[sl], k=k, distance_upper_bound=radius)
        out[sl] = _fit_rows(verts[sl], vnormals[sl], t1[sl], t2[sl], pts, snormals, dist.reshape(-1, k),
                            idx.reshape(-1, k), float(radius))
    return out


class _SampleGrid:
    """The samples bucketed in cubic cells at least `radius` wide, sorted by cell: a vertex's neighbours
    within the radius lie in its cell's 3 x 3 x 3 block, whose z-runs are 9 ranges of the sorted keys. On a
    room it finds a ball's samples in a fraction of a k-d tree query's time, and the same ones
    (`bench/cues/curvature.py`)."""

    def __init__(self, pts: np.ndarray, verts: np.ndarray, radius: float):
        lo = np.minimum(pts.min(axis=0), verts.min(axis=0))
        hi = np.maximum(pts.max(axis=0), verts.max(axis=0))
        # At most 2^20 cells an axis (keys fit int64); a wider cell only adds candidates, each one is checked.
        self.cell = max(float(radius), float((hi - lo).max()) / 2**20)
        self.lo = lo - self.cell  # one empty cell below every axis: a block never leaves the grid
        self.dims = ((hi - self.lo) // self.cell).astype(np.int64) + 3
        keys = _cell_keys(pts, self.lo, self.cell, self.dims)
        self.order = np.argsort(keys, kind="stable")
        self.keys = keys[self.order]


@njit(cache=True, nogil=True)
def _cell_keys(x: np.ndarray, lo: np.ndarray, cell: float, dims: np.ndarray) -> np.ndarray:
    """Linear cell index of every point, z last: a column's cells are consecutive keys."""
    keys = np.empty(len(x), np.int64)
    for i in range(len(x)):
        cx = int((x[i, 0] - lo[0]) / cell)
        cy = int((x[i, 1] - lo[1]) / cell)
        cz = int((x[i, 2] - lo[2]) / cell)
        keys[i] = (cx * dims[1] + cy) * dims[2] + cz
    return keys


def _sample_surface(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted uniform surface samples and their face indices (deterministic for a given rng)."""
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    cdf = np.cumsum(area)
    fidx = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right").clip(0, len(area) - 1)
    r1, r2 = rng.random(n), rng.random(n)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    return _points_on_faces(verts, np.asarray(mesh.faces, dtype=np.int64), fidx, r1, r2), fidx


@njit(cache=True, nogil=True)
def _points_on_faces(verts: np.ndarray, faces: np.ndarray, fidx: np.ndarray, r1: np.ndarray,
                     r2: np.ndarray) -> np.ndarray:
    """v0 + r1 (v1 - v0) + r2 (v2 - v0) on each sample's face, (r1, r2) folded onto the triangle where r1 + r2
    > 1: numpy's float64 expression on the gathered triangles, one sample at a time, without the n x 3 x 3
    copy of the triangles (ICL: 0.15 of the 0.64 CPU-s its curvature took;
    tests/worker/inputs/test_curvature.py: the same bits)."""
    out = np.empty((len(fidx), 3))
    for i in range(len(fidx)):
        s, t = r1[i], r2[i]
        if s + t > 1.0:
            s, t = 1.0 - s, 1.0 - t
        a, b, c = faces[fidx[i], 0], faces[fidx[i], 1], faces[fidx[i], 2]
        for k in range(3):
            v0 = verts[a, k]
            out[i, k] = v0 + s * (verts[b, k] - v0) + t * (verts[c, k] - v0)
    return out


def _tangent_frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents orthogonal to each unit normal (N x 3 each)."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


@njit(cache=True, nogil=True)
def _fit_rows(
    p: np.ndarray, n: np.ndarray, t1: np.ndarray, t2: np.ndarray, pts: np.ndarray, snormals: np.ndarray,
    dist: np.ndarray, idx: np.ndarray, radius: float,
) -> np.ndarray:
    """The fits of a batch of vertices from a k-d tree's rows (nearest first, misses last at infinity)."""
    out = np.zeros((len(p), 2), np.float32)
    for b in range(len(p)):
        m = 0
        while m < dist.shape[1] and np.isfinite(dist[b, m]):
            m += 1
        out[b, 0], out[b, 1] = _fit_one(p[b], n[b], t1[b], t2[b], pts, snormals, dist[b], idx[b], m, radius)
    return out


@njit(cache=True, nogil=True)
def _fit_in_grid(p: np.ndarray, n: np.ndarray, t1: np.ndarray, t2: np.ndarray, pts: np.ndarray,
                 snormals: np.ndarray, keys: np.ndarray, lo: np.ndarray, cell: float, dims: np.ndarray,
                 radius: float, k: int) -> np.ndarray:
    """The fits of every vertex on its k nearest samples strictly within the radius, nearest first (what a k-d
    tree query with that bound returns), found in the grid (_SampleGrid: samples sorted by cell)."""
    out = np.zeros((len(p), 2), np.float32)
    r2 = radius * radius
    near_d2 = np.empty(256)
    near_q = np.empty(256, np.int64)
    first_q = np.empty(9, np.int64)  # the block's 9 z-runs of sorted samples: [first_q, end_q)
    end_q = np.empty(9, np.int64)
    for b in range(len(p)):
        cx = int((p[b, 0] - lo[0]) / cell)
        cy = int((p[b, 1] - lo[1]) / cell)
        cz = int((p[b, 2] - lo[2]) / cell)
        candidates = 0
        run = 0
        for ix in range(cx - 1, cx + 2):
            for iy in range(cy - 1, cy + 2):
                first = (ix * dims[1] + iy) * dims[2] + cz - 1
                first_q[run] = np.searchsorted(keys, first)
                end_q[run] = np.searchsorted(keys, first + 2, side="right")
                candidates += end_q[run] - first_q[run]
                run += 1
        if candidates > len(near_d2):  # a crowded spot: buffers for every candidate, before the scan
            near_d2 = np.empty(candidates)
            near_q = np.empty(candidates, np.int64)
        m = _ball(p[b], pts, first_q, end_q, r2, near_d2, near_q)
        if m > 64:  # a crowded spot: a merge sort (the insertion sort's cost grows with m^2)
            order = np.argsort(near_d2[:m], kind="mergesort")[:k]
            m = len(order)
            near_d2[:m], near_q[:m] = near_d2[order], near_q[order]
        else:
            _insertion_sort(near_d2, near_q, m)
            m = min(m, k)
        out[b, 0], out[b, 1] = _fit_one(
            p[b], n[b], t1[b], t2[b], pts, snormals, np.sqrt(near_d2[:m]), near_q, m, radius
        )
    return out


@njit(cache=True, nogil=True)
def _ball(
    c: np.ndarray, pts: np.ndarray, first_q: np.ndarray, end_q: np.ndarray, r2: float, near_d2: np.ndarray,
    near_q: np.ndarray,
) -> int:
    """The samples of the runs [first_q, end_q) strictly within sqrt(r2) of c, in run order, written to
    near_d2 (squared distances) and near_q (indices), which hold every candidate; returns how many. A function
    of its own, with buffers that cannot change under it: grown inside the scan (as before), they cost the
    kitchen's curvature ~40% more CPU (bench/cues/curvature.py)."""
    m = 0
    for run in range(len(first_q)):
        for q in range(first_q[run], end_q[run]):
            dx, dy, dz = pts[q, 0] - c[0], pts[q, 1] - c[1], pts[q, 2] - c[2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < r2:
                near_d2[m] = d2
                near_q[m] = q
                m += 1
    return m


@njit(cache=True, nogil=True)
def _insertion_sort(d2: np.ndarray, q: np.ndarray, m: int) -> None:
    """Sort d2[:m] increasing, q[:m] along, in place, stable: for a ball's ~50 samples, where a library sort's
    allocations cost more than the comparisons."""
    for i in range(1, m):
        d, s = d2[i], q[i]
        j = i - 1
        while j >= 0 and d2[j] > d:
            d2[j + 1], q[j + 1] = d2[j], q[j]
            j -= 1
        d2[j + 1], q[j + 1] = d, s


@njit(cache=True, nogil=True)
def _fit_one(
    p: np.ndarray, n: np.ndarray, t1: np.ndarray, t2: np.ndarray, pts: np.ndarray, snormals: np.ndarray,
    dist: np.ndarray, idx: np.ndarray, m: int, radius: float,
) -> tuple[float, float]:
    """One vertex's (k1, k2) from its m neighbours (distances and sample indices, nearest first): weighted
    least squares of h = a u^2 + b uv + c v^2 + d u + e v + g, then the shape operator's eigenvalues; 0 when <
    8."""
    sigma = radius / 2.0
    A = np.zeros((6, 6))
    rhs = np.zeros(6)
    phi = np.empty(6)
    count = 0
    for j in range(m):
        q = idx[j]
        agree = snormals[q, 0] * n[0] + snormals[q, 1] * n[1] + snormals[q, 2] * n[2]
        if not abs(agree) > 0.35:
            continue
        w = np.exp(-0.5 * (dist[j] / sigma) ** 2)
        if w > 0:
            count += 1
        dx, dy, dz = pts[q, 0] - p[0], pts[q, 1] - p[1], pts[q, 2] - p[2]
        # Scale coordinates by the radius so the normal equations are well conditioned for any mesh unit.
        u = (dx * t1[0] + dy * t1[1] + dz * t1[2]) / radius
        v = (dx * t2[0] + dy * t2[1] + dz * t2[2]) / radius
        h = (dx * n[0] + dy * n[1] + dz * n[2]) / radius
        phi[0], phi[1], phi[2], phi[3], phi[4], phi[5] = u * u, u * v, v * v, u, v, 1.0
        for r in range(6):
            wr = w * phi[r]
            rhs[r] += wr * h
            for c in range(6):
                A[r, c] += wr * phi[c]
    if count < 8:
        return 0.0, 0.0
    trace = 0.0
    for r in range(6):
        trace += A[r, r]
    for r in range(6):
        A[r, r] += 1e-9 * (trace + 1e-12)
    coef = np.linalg.solve(A, rhs)
    return _principal(coef[0], coef[1], coef[2], coef[3], coef[4], radius)


@njit(cache=True, nogil=True)
def _principal(a: float, b: float, c: float, du: float, dv: float, radius: float) -> tuple[float, float]:
    """(k1, k2) of the Monge patch h = a u^2 + b uv + c v^2 + du u + dv v at the origin, 0 if not finite."""
    # Back to mesh units: h/r = a (u/r)^2 + ... => second derivatives scale by 1/r, first are unitless.
    a, b, c = a / radius, b / radius, c / radius
    E, F, G = 1 + du * du, du * dv, 1 + dv * dv
    root = np.sqrt(1 + du * du + dv * dv)
    L, M, N = 2 * a / root, b / root, 2 * c / root
    det_i = E * G - F * F
    # Shape operator S = I^-1 II (2x2, not symmetric); its eigenvalues are real (similar to a symmetric
    # matrix).
    s11 = (G * L - F * M) / det_i
    s12 = (G * M - F * N) / det_i
    s21 = (E * M - F * L) / det_i
    s22 = (E * N - F * M) / det_i
    tr, det = s11 + s22, s11 * s22 - s12 * s21
    disc = np.sqrt(max(tr * tr / 4 - det, 0.0))
    e_hi, e_lo = tr / 2 + disc, tr / 2 - disc
    # h is measured along the normal, so a convex bump (surface bending away from the normal) has negative
    # eigenvalues; flip so convex is positive, and keep k1 >= k2.
    k1, k2 = -e_lo, -e_hi
    if not (np.isfinite(k1) and np.isfinite(k2)):
        return 0.0, 0.0
    return k1, k2
