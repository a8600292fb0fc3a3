"""The surfaces of a point cloud read from its points, for levelling where its Poisson mesh shows no plane.

Frames and units: the cloud's source frame and units; every length here is relative to the cloud's diagonal,
so no unit is assumed. A SLAM cloud (Project Aria's semi-dense points) samples image edges, not surfaces:
screened Poisson over it gives a surface with no dominant plane, yet the edges on a floor, a wall or a table
still lie in their plane. At a coarse scale (tens of neighbours, centimetres apart) the principal axes of a
neighbourhood show that plane:

1. *Density*: the points are averaged per voxel (`VOXEL_FRACTION` of the diagonal), so each sample stands for
   the same area (one voxel face) however densely the sensor saw it (SLAM points crowd on strong texture).
2. *Normals*: PCA of each sample's `NEIGHBOURS` nearest samples; the smallest axis is the normal where it is
   clearly smaller than the others (`PLANARITY_MAX`; a lone edge or a corner has no normal), turned towards
   the centre of the bounding box as the mesh's normals are (a room scanned from inside: floors face up), or
   towards the camera at the source origin in a single depth frame (`single_view`).
3. The samples (centroid, normal, a voxel face of area) then stand in for a mesh's faces in
   `gravity.estimate_up` and `gravity.guess_candidates`: the same plane families, floor candidates,
   evidence terms and calibrated decision.

Edges cover a floor sparsely, so an edge-only cloud rarely shows the floor share a room needs: its planes then
order the candidates of a refusal (or confirm the format's up), never level it on their own.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from services.core.ingest.frame.gravity import SurfaceSamples
from services.core.ingest.frame.single_view import single_view

VOXEL_FRACTION = 0.004  # of the bounding-box diagonal: ~7 cm in Aria's 19 m-diagonal SLAM cloud
NEIGHBOURS = 40
# smallest PCA eigenvalue over their sum: below it a neighbourhood is a plane (0: flat, 1/3: isotropic)
PLANARITY_MAX = 0.1
MIN_SAMPLES = 200
_HULL_POINTS = 5_000


def voxel_means(points: np.ndarray, voxel: float) -> np.ndarray:
    """The mean of the points in each occupied voxel of side `voxel` (source units), in a stable order."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.reshape(-1), points)
    return sums / counts[:, None]


def pca_normals(samples: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal, planarity) per sample from its `k` nearest samples: the smallest principal axis and the
    smallest eigenvalue over the sum (0 for a flat neighbourhood, 1/3 for an isotropic one)."""
    _, nearest = cKDTree(samples).query(samples, k=min(k, len(samples)))
    hood = samples[nearest]
    centred = hood - hood.mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    return vectors[:, :, 0], values[:, 0] / np.maximum(values.sum(axis=1), 1e-300)


def point_samples(points: np.ndarray) -> SurfaceSamples | None:
    """The cloud's planar samples as surface elements for levelling (module docstring); None when the cloud
    is too small or shows no plane."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < MIN_SAMPLES:
        return None
    diagonal = float(np.linalg.norm(np.ptp(pts, axis=0)))
    if diagonal <= 0:
        return None
    voxel = VOXEL_FRACTION * diagonal
    samples = voxel_means(pts, voxel)
    if len(samples) < MIN_SAMPLES:
        return None
    normals, planarity = pca_normals(samples, NEIGHBOURS)
    flat = planarity < PLANARITY_MAX
    if flat.sum() < MIN_SAMPLES:
        return None
    # a single depth frame faces its camera, at the source origin; a room scanned from inside, its middle
    centre = (np.zeros(3) if single_view(samples) is not None
              else 0.5 * (samples.min(axis=0) + samples.max(axis=0)))
    inward = np.where(np.einsum("ij,ij->i", centre - samples, normals) < 0, -1.0, 1.0)
    step = len(samples) // _HULL_POINTS + 1
    return SurfaceSamples((normals * inward[:, None])[flat], np.full(int(flat.sum()), voxel * voxel),
                          samples[flat], samples, samples[::step])
