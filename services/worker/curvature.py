"""Per-vertex principal curvatures of a mesh by weighted quadric fitting on a metric neighbourhood. Pure numpy/scipy.

Why not pymeshlab's APSS (what the Omnidata annotator used): APSS' filter scale is a multiple of the local point
spacing, so the curvature it reports depends on how densely the scan was tessellated; the JobSpec asks for a
neighbourhood radius in metres (`curvature_radius_m`), which a quadric fit honours directly and which is
vectorised here (no per-vertex Python). The estimator:

1. sample the surface uniformly (area-weighted, fixed seed) at a spacing of radius/4, so every neighbourhood holds
   ~50 samples whatever the tessellation (at most MAX_SAMPLES; meshes with more vertices add their vertices);
2. for each vertex, take up to MAX_NEIGHBOURS samples within the radius, Gaussian-weighted by distance
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
    tree = cKDTree(pts)
    out = np.zeros((len(verts), 2), dtype=np.float32)
    for s in range(0, len(verts), CHUNK):
        sl = slice(s, min(s + CHUNK, len(verts)))
        out[sl] = _fit_chunk(verts[sl], vnormals[sl], pts, snormals, tree, radius)
    return out


def _sample_surface(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted uniform surface samples and their face indices (deterministic for a given rng)."""
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    cdf = np.cumsum(area)
    fidx = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right").clip(0, len(area) - 1)
    tri = np.asarray(mesh.triangles, dtype=np.float64)[fidx]
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1.0  # fold the unit square onto the triangle
    r1[flip], r2[flip] = 1.0 - r1[flip], 1.0 - r2[flip]
    pts = tri[:, 0] + r1[:, None] * (tri[:, 1] - tri[:, 0]) + r2[:, None] * (tri[:, 2] - tri[:, 0])
    return pts, fidx


def _tangent_frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents orthogonal to each unit normal (N x 3 each)."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def _fit_chunk(p: np.ndarray, n: np.ndarray, pts: np.ndarray, snormals: np.ndarray, tree: cKDTree,
               radius: float) -> np.ndarray:
    """Quadric fits for a batch of vertices; returns float32 B x 2 (k1 >= k2, positive convex)."""
    k = min(MAX_NEIGHBOURS, len(pts))
    dist, idx = tree.query(p, k=k, distance_upper_bound=radius)
    dist, idx = dist.reshape(len(p), k), idx.reshape(len(p), k)
    t1, t2 = _tangent_frames(n)
    return _fit_kernel(p, n, t1, t2, pts, snormals, dist, idx, float(radius))


@njit(cache=True, nogil=True)
def _fit_kernel(p: np.ndarray, n: np.ndarray, t1: np.ndarray, t2: np.ndarray, pts: np.ndarray,
                snormals: np.ndarray, dist: np.ndarray, idx: np.ndarray, radius: float) -> np.ndarray:
    """One vertex at a time (compiled: no B x k x 6 temporaries): weighted least squares of
    h = a u^2 + b uv + c v^2 + d u + e v + g on the neighbours, then the shape operator's eigenvalues."""
    out = np.zeros((len(p), 2), np.float32)
    sigma = radius / 2.0
    phi = np.empty(6)
    for b in range(len(p)):
        A = np.zeros((6, 6))
        rhs = np.zeros(6)
        count = 0
        for j in range(dist.shape[1]):
            dj = dist[b, j]
            if not np.isfinite(dj):
                continue
            q = idx[b, j]
            agree = snormals[q, 0] * n[b, 0] + snormals[q, 1] * n[b, 1] + snormals[q, 2] * n[b, 2]
            if not abs(agree) > 0.35:
                continue
            w = np.exp(-0.5 * (dj / sigma) ** 2)
            if w > 0:
                count += 1
            dx, dy, dz = pts[q, 0] - p[b, 0], pts[q, 1] - p[b, 1], pts[q, 2] - p[b, 2]
            # Scale coordinates by the radius so the normal equations are well conditioned for any mesh unit.
            u = (dx * t1[b, 0] + dy * t1[b, 1] + dz * t1[b, 2]) / radius
            v = (dx * t2[b, 0] + dy * t2[b, 1] + dz * t2[b, 2]) / radius
            h = (dx * n[b, 0] + dy * n[b, 1] + dz * n[b, 2]) / radius
            phi[0], phi[1], phi[2], phi[3], phi[4], phi[5] = u * u, u * v, v * v, u, v, 1.0
            for r in range(6):
                wr = w * phi[r]
                rhs[r] += wr * h
                for c in range(6):
                    A[r, c] += wr * phi[c]
        if count < 8:
            continue
        trace = 0.0
        for r in range(6):
            trace += A[r, r]
        for r in range(6):
            A[r, r] += 1e-9 * (trace + 1e-12)
        coef = np.linalg.solve(A, rhs)
        out[b, 0], out[b, 1] = _principal(coef[0], coef[1], coef[2], coef[3], coef[4], radius)
    return out


@njit(cache=True, nogil=True)
def _principal(a: float, b: float, c: float, du: float, dv: float, radius: float) -> tuple[float, float]:
    """(k1, k2) of the Monge patch h = a u^2 + b uv + c v^2 + du u + dv v at the origin, 0 if not finite."""
    # Back to mesh units: h/r = a (u/r)^2 + ... => second derivatives scale by 1/r, first are unitless.
    a, b, c = a / radius, b / radius, c / radius
    E, F, G = 1 + du * du, du * dv, 1 + dv * dv
    root = np.sqrt(1 + du * du + dv * dv)
    L, M, N = 2 * a / root, b / root, 2 * c / root
    det_i = E * G - F * F
    # Shape operator S = I^-1 II (2x2, not symmetric); its eigenvalues are real (similar to a symmetric matrix).
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
