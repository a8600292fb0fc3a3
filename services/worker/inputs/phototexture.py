"""Photo-textured views: rgb for any camera from a capture's photos projected onto the mesh.

For each pixel of a rendered view, the surface point it sees (world metres, from the pass set's depth) is
projected into the capture's photos. A photo colours the point only where it saw it: the ray from the photo's
camera centre to the point must first meet the mesh at the point (a depth test, within DEPTH_TOLERANCE of the
distance). Of the photos that saw it, the `k` with the largest weight are blended, weight = cos(angle between
the surface normal and the direction to the photo's camera) x cos(angle between the view's ray and the photo's
ray) / distance^2: head-on, close photos from nearby viewpoints count most; a photo seeing the surface more
obliquely than MIN_COS is not used. Pixels no photo saw are left black
and outside `photo_coverage` (the mask_photo cue). Photos are ranked per view first (how many of the view's
sampled surface points they see) and only the best CANDIDATES_PER_K * k are tested per pixel.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from services.core.ingest.capture.distortion import project_to_photo
from services.core.ingest.capture.model import Capture
from services.core.ingest.capture.photos import Photo
from services.core.ingest.capture.resample import sample_photo
from services.worker.passes import ViewGeometry, ViewPasses

DEPTH_TOLERANCE_M = 0.02  # plus 1% of the distance: TSDF meshes and photo poses are this good, not better
CANDIDATES_PER_K = 3
# a photo seeing the surface more obliquely than ~78 degrees smears it (and its silhouette) over it
MIN_COS = 0.2
PROBE = 24  # probe points per side when ranking photos for a view


class PhotoTexturer:
    """Projects one capture's photos (world frame) onto one world-frame mesh."""

    def __init__(self, mesh: trimesh.Trimesh, capture: Capture, *, k: int = 3):
        self.mesh = mesh
        self.capture = capture
        self.k = k
        self.centres = np.stack([f.center for f in capture.frames])

    def _seen_by(self, j: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(photo pixel coordinates (n, 2), bool seen) of world points in frame j: in the photo and not
        hidden."""
        frame = self.capture.frames[j]
        assert frame.K is not None and frame.width is not None and frame.height is not None
        cam = points @ frame.world_to_camera[:3, :3].T + frame.world_to_camera[:3, 3]
        uv, front = project_to_photo(frame.K, frame.distortion, frame.distortion_params, cam)
        inside = front & (uv[:, 0] >= 0.5) & (uv[:, 0] <= frame.width - 0.5) & (uv[:, 1] >= 0.5) \
            & (uv[:, 1] <= frame.height - 0.5)
        idx = np.flatnonzero(inside)
        if len(idx):
            d = points[idx] - self.centres[j]
            dist = np.linalg.norm(d, axis=1)
            origins = np.broadcast_to(self.centres[j], d.shape)
            tri, ray, loc = self.mesh.ray.intersects_id(origins, d / dist[:, None], multiple_hits=False,
                                                         return_locations=True)
            first = np.full(len(idx), np.inf)
            first[ray] = np.linalg.norm(loc - origins[ray], axis=1)
            hidden = first < dist - (DEPTH_TOLERANCE_M + 0.01 * dist)
            inside[idx[hidden]] = False
        return uv, inside

    def _normals(
        self, centre: np.ndarray, view_dir: np.ndarray, passes: ViewPasses, idx: np.ndarray
    ) -> np.ndarray:
        """Unit surface normals, facing the view, of the surface points idx (the pass set's, else the mesh's
        faces along the view's rays: the rgb cue alone does not read normals back)."""
        if passes.normal_world is not None:
            n = passes.normal_world.reshape(-1, 3)[idx].astype(np.float64)
        else:
            n = np.zeros((len(idx), 3))
            tri, ray = self.mesh.ray.intersects_id(np.broadcast_to(centre, view_dir.shape), view_dir,
                                                   multiple_hits=False)[:2]
            n[ray] = np.asarray(self.mesh.face_normals)[tri]
        flip = np.einsum("ij,ij->i", n, view_dir) > 0
        n[flip] *= -1.0
        return n

    def rank(self, points: np.ndarray) -> np.ndarray:
        """Frame indices, best first, by how many of the (probe) points each sees."""
        counts = np.array([self._seen_by(j, points)[1].sum() for j in range(len(self.capture.frames))])
        order = np.argsort(-counts, kind="stable")
        return order[counts[order] > 0]

    def paint(self, view: ViewGeometry, passes: ViewPasses,
              photo: Callable[[int], Photo]) -> tuple[np.ndarray, np.ndarray]:
        """(uint8 H x W x 3 rgb, bool H x W covered) of the view (see the module docstring)."""
        n = view.resolution
        points = passes.position_world().reshape(-1, 3).astype(np.float64)
        hit = np.isfinite(points).all(axis=1)
        idx = np.flatnonzero(hit)
        rgb = np.zeros((n * n, 3), dtype=np.float32)
        covered = np.zeros(n * n, dtype=bool)
        if not len(idx):
            return rgb.reshape(n, n, 3).astype(np.uint8), covered.reshape(n, n)
        step = max(1, len(idx) // (PROBE * PROBE))
        candidates = self.rank(points[idx[::step]])[: CANDIDATES_PER_K * self.k]
        pts = points[idx]
        view_dir = pts - view.center
        view_dir /= np.linalg.norm(view_dir, axis=1, keepdims=True)
        normals = self._normals(view.center, view_dir, passes, idx)
        weights = np.zeros((len(candidates), len(idx)), dtype=np.float64)
        colours = np.zeros((len(candidates), len(idx), 3), dtype=np.float32)
        for c, j in enumerate(candidates):
            uv, seen = self._seen_by(int(j), pts)
            if not seen.any():
                continue
            to_photo = self.centres[j] - pts
            dist = np.linalg.norm(to_photo, axis=1)
            to_photo /= dist[:, None]
            facing = np.einsum("ij,ij->i", normals, to_photo)
            w = (
                facing
                * np.clip(-np.einsum("ij,ij->i", view_dir, to_photo), 0, None)
                / np.maximum(dist, 1e-3) ** 2
            )
            weights[c] = np.where(seen & (facing >= MIN_COS), w, 0.0)
            colours[c, seen] = sample_photo(photo(int(j)), uv[seen])
        if len(candidates) > self.k:  # keep the k largest weights per pixel
            cut = np.partition(weights, -self.k, axis=0)[-self.k]
            weights = np.where(weights >= cut[None, :], weights, 0.0)
        total = weights.sum(axis=0)
        ok = total > 0
        blended = np.einsum("cn,cnk->nk", weights[:, ok], colours[:, ok]) / total[ok, None]
        rgb[idx[ok]] = blended
        covered[idx[ok]] = True
        return np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(n, n, 3), covered.reshape(n, n)
