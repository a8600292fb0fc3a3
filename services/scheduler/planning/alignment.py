"""How well a photo agrees with the scan's geometry seen from the photo's camera: the alignment score.

Where the rendered geometry has an edge (a depth discontinuity, a crease between differently facing surfaces,
a silhouette against nothing), a photo taken from that camera nearly always has a brightness edge too; a photo
that is misregistered by a few pixels has its edges beside them. The score is the mean photo gradient across
the geometric edges (its component along the edge map's own gradient, so texture running along or beside an
edge counts little) at edge pixels, divided by the mean photo gradient magnitude over the whole covered image
times 2/pi (the mean of |cos| of a random angle): about 1 when the edges are unrelated (chance), higher the
better they line up. Cast at ALIGN_PX x ALIGN_PX through the view's pinhole camera (metres,
OpenCV axes), the photo resampled to the same camera (services.core.ingest.capture.resample).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_erosion, gaussian_filter, sobel

from services.core.domain.camera import intrinsics
from services.core.ingest.capture.model import CaptureFrame
from services.core.ingest.capture.photos import Photo, load_photo
from services.core.ingest.capture.resample import photo_for_view
from services.scheduler.planning.visibility import MeshQueries

ALIGN_PX = 192
DEPTH_JUMP = 0.04  # relative depth change between neighbours that makes an occlusion edge
CREASE_DEG = 35.0  # normal change between neighbours that makes a crease edge
MIN_EDGE_PIXELS = 30


def cast_view(
    q: MeshQueries, world_to_camera: np.ndarray, fov: float, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """(z-depth metres, inf = none; unit face normals, 0 = none) of a square pinhole view, size x size."""
    K = intrinsics(fov, size)
    g = (np.arange(size) + 0.5 - K[0, 2]) / K[0, 0]
    d_cam = np.stack(np.broadcast_arrays(g[None, :], g[:, None], np.ones((size, size))), axis=-1).reshape(
        -1, 3
    )
    d_cam = d_cam / np.linalg.norm(d_cam, axis=1, keepdims=True)
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    origins = np.broadcast_to(-R.T @ t, d_cam.shape)
    dist, face = q.first_hit(np.ascontiguousarray(origins), d_cam @ R)
    z = (dist * d_cam[:, 2]).reshape(size, size)
    normals = np.zeros((size * size, 3))
    hit = face >= 0
    normals[hit] = np.asarray(q.mesh.face_normals)[face[hit]]
    return z, normals.reshape(size, size, 3)


def geometry_edges(z: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """bool H x W: pixels on either side of an occlusion edge, a crease, or a surface/nothing boundary."""
    hit = np.isfinite(z)
    edges = np.zeros(z.shape, dtype=bool)
    cos_crease = np.cos(np.radians(CREASE_DEG))
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        za, zb, ha, hb = z[tuple(a)], z[tuple(b)], hit[tuple(a)], hit[tuple(b)]
        with np.errstate(invalid="ignore"):
            jump = (ha != hb) | (ha & hb & (np.abs(za - zb) > DEPTH_JUMP * np.minimum(za, zb)))
        crease = ha & hb & (np.einsum("ijk,ijk->ij", normals[tuple(a)], normals[tuple(b)]) < cos_crease)
        e = jump | crease
        edges[tuple(a)] |= e
        edges[tuple(b)] |= e
    return edges


def gradient(image: np.ndarray, blur: float) -> tuple[np.ndarray, np.ndarray]:
    """(d/dx, d/dy) Sobel derivatives of a blurred float image."""
    smooth = gaussian_filter(image.astype(np.float32), blur)
    return sobel(smooth, axis=1), sobel(smooth, axis=0)


def scoring_photo(path: str, frame: CaptureFrame, fov: float, size: int = ALIGN_PX) -> Photo:
    """The frame's photo decoded no larger than a score at `size` pixels and field of view `fov` needs."""
    return load_photo(path, frame, float(intrinsics(fov, size)[0, 0]))


def alignment_score(q: MeshQueries, photo: Photo, frame: CaptureFrame, world_to_camera: np.ndarray,
                    fov: float,
                    size: int = ALIGN_PX) -> float | None:
    """The score of one view whose camera shares the frame's centre (see the module docstring); None when the
    view shows too few geometric edges inside the photo to tell."""
    z, normals = cast_view(q, world_to_camera, fov, size)
    edges = geometry_edges(z, normals)
    rgb, covered = photo_for_view(photo, frame, intrinsics(fov, size), world_to_camera, size, size)
    inner = binary_erosion(covered, iterations=2)
    at_edges = edges & inner
    if at_edges.sum() < MIN_EDGE_PIXELS or not inner.any():
        return None
    gx, gy = gradient(rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32), 0.7)
    ex, ey = gradient(edges, 1.0)  # across the edge lines
    across = np.abs(gx * ex + gy * ey) / (np.hypot(ex, ey) + 1e-9)
    mean = float(np.hypot(gx, gy)[inner].mean()) * 2.0 / np.pi
    return float(across[at_edges].mean() / mean) if mean > 0 else None


def score_summary(scores: list[float | None], threshold: float) -> dict[str, object]:
    """Distribution of scores (job.json, the dashboard's histogram): quantiles, a 10-bin histogram, drops."""
    known = np.array([s for s in scores if s is not None], dtype=np.float64)
    out: dict[str, object] = {"views": len(scores), "scored": int(len(known)), "threshold": threshold}
    if len(known):
        q = np.quantile(known, [0.0, 0.25, 0.5, 0.75, 1.0])
        out.update(min=float(q[0]), p25=float(q[1]), median=float(q[2]), p75=float(q[3]), max=float(q[4]))
        counts, bins = np.histogram(known, bins=10)
        out["histogram"] = {"counts": counts.tolist(), "edges": [round(float(b), 4) for b in bins]}
        out["below_threshold"] = int((known < threshold).sum()) if threshold > 0 else 0
    return out
