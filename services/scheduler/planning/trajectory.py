"""Trajectory views: a smooth camera path per point, frames at regular spacing, each fixated on the point.

World metres, radians. For each point:
  1. the cameras that see it (at most max_views, chosen by the rng) are ordered into an open path:
     nearest neighbour from the camera farthest from their centroid, then 2-opt until no move
     shortens the path;
  2. a natural cubic spline (C2, scipy CubicSpline) through the camera positions, parametrised by
     chord length, is re-parametrised by arc length (dense table, 256 samples per segment);
  3. frames every trajectory_spacing_m along the arc (when that exceeds trajectory_max_frames,
     that many frames evenly spread over the whole path), each looking at the point;
  4. roll: a value ~ U[-roll_max, roll_max] per camera, interpolated as roll_max * sin(phi(t)) with
     phi a C2 spline through arcsin(roll_i / roll_max), so it is smooth, exact at the cameras and never
     leaves the bounds; the fov is one truncated-normal draw per point (a constant zoom per clip);
  5. in_sight per frame by a line-of-sight ray to the point (the path may pass behind an obstacle
     between two cameras); camera_idx = the nearest camera to the frame.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from services.core.jobspec import ViewSpec
from services.scheduler.planning.views import (
    ViewArrays,
    cap_views,
    look_at_batch,
    obliqueness,
    truncated_normal,
)
from services.scheduler.planning.visibility import MeshQueries

DENSE_PER_SEGMENT = 256


def order_path(xyz: np.ndarray) -> np.ndarray:
    """Indices ordering the points into a short open path (nearest neighbour + 2-opt)."""
    n = len(xyz)
    if n <= 2:
        return np.arange(n)
    D = np.linalg.norm(xyz[:, None, :] - xyz[None, :, :], axis=2)
    start = int(np.argmax(np.linalg.norm(xyz - xyz.mean(axis=0), axis=1)))
    path = [start]
    free = np.ones(n, dtype=bool)
    free[start] = False
    for _ in range(n - 1):
        d = np.where(free, D[path[-1]], np.inf)
        nxt = int(np.argmin(d))
        path.append(nxt)
        free[nxt] = False
    p = np.array(path)
    for _ in range(100):
        improved = False
        for i in range(-1, n - 2):
            j = np.arange(i + 2, n)
            # reverse p[i+1..j]: edges (i, i+1) and (j, j+1) become (i, j) and (i+1, j+1)
            old = np.zeros(len(j))
            new = np.zeros(len(j))
            if i >= 0:
                old += D[p[i], p[i + 1]]
                new += D[p[i], p[j]]
            has_next = j + 1 < n
            jn = np.minimum(j + 1, n - 1)
            old += np.where(has_next, D[p[j], p[jn]], 0.0)
            new += np.where(has_next, D[p[i + 1], p[jn]], 0.0)
            gain = old - new
            k = int(np.argmax(gain))
            if gain[k] > 1e-12:
                jj = int(j[k])
                p[i + 1:jj + 1] = p[i + 1:jj + 1][::-1]
                improved = True
        if not improved:
            break
    return p


def camera_path(waypoints: np.ndarray) -> tuple[CubicSpline | None, np.ndarray]:
    """Natural cubic spline through the waypoints over chord length; (None, [0]) for a single point."""
    keep = np.concatenate([[True], np.linalg.norm(np.diff(waypoints, axis=0), axis=1) > 1e-9])
    w = waypoints[keep]
    if len(w) < 2:
        return None, np.zeros(1)
    t = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(w, axis=0), axis=1))])
    return CubicSpline(t, w, bc_type="natural"), t


def arc_length_frames(spline: CubicSpline, knots: np.ndarray, spacing: float, max_frames: int) -> np.ndarray:
    """Spline parameters of frames at equal arc-length spacing along the path (see module docstring)."""
    ts = np.concatenate([
        np.linspace(knots[i], knots[i + 1], DENSE_PER_SEGMENT, endpoint=False) for i in range(len(knots) - 1)
    ] + [knots[-1:]])
    pts = spline(ts)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    length = float(s[-1])
    n = int(np.floor(length / spacing + 1e-9)) + 1
    if n > max_frames:
        n = max_frames
        targets = np.linspace(0.0, length, n)
    else:
        targets = np.arange(n) * spacing
    return np.interp(targets, s, ts)


def trajectory(
    positions: np.ndarray,
    normals: np.ndarray,
    visible: tuple[np.ndarray, ...],
    cameras: np.ndarray,
    spec: ViewSpec,
    max_views: int | None,
    q: MeshQueries,
    tol: float,
    rng: np.random.Generator,
) -> ViewArrays:
    """Frames of a smooth fixated path per point (module docstring); v numbers the frames."""
    rmax = np.radians(spec.roll_max_deg)
    fov_args = (np.radians(spec.fov_mean_deg), np.radians(spec.fov_std_deg),
                np.radians(spec.fov_min_deg), np.radians(spec.fov_max_deg))
    tree = cKDTree(cameras)
    P: list[np.ndarray] = []
    F: list[np.ndarray] = []
    R: list[np.ndarray] = []
    FOV: list[np.ndarray] = []
    for p, cams in enumerate(visible):
        cams = cap_views(cams, max_views, rng)
        way = cameras[cams][order_path(cameras[cams])]
        rolls = rng.uniform(-rmax, rmax, len(way))
        fov = float(truncated_normal(rng, *fov_args, 1)[0])
        spline, knots = camera_path(way)
        if spline is None:
            frames, frame_roll = way[:1], rolls[:1]
        else:
            t = arc_length_frames(spline, knots, spec.trajectory_spacing_m, spec.trajectory_max_frames)
            frames = spline(t)
            if rmax > 0:
                keep = np.concatenate([[True], np.linalg.norm(np.diff(way, axis=0), axis=1) > 1e-9])
                phi = CubicSpline(knots, np.arcsin(np.clip(rolls[keep] / rmax, -1, 1)), bc_type="natural")
                frame_roll = rmax * np.sin(phi(t))
            else:
                frame_roll = np.zeros(len(t))
        ok = np.linalg.norm(frames - positions[p], axis=1) > 1e-6  # never look at the point from itself
        P.append(np.full(int(ok.sum()), p, dtype=np.int64))
        F.append(frames[ok])
        R.append(frame_roll[ok])
        FOV.append(np.full(int(ok.sum()), fov))
    if not P:
        z = np.zeros(0)
        return ViewArrays(z.astype(np.int64), z.astype(np.int64), z.astype(np.int64), np.zeros((0, 4, 4)),
                          z, z, z, z.astype(bool))
    pidx = np.concatenate(P)
    frames = np.concatenate(F)
    roll = np.concatenate(R)
    fov = np.concatenate(FOV)
    counts = np.bincount(pidx, minlength=len(visible))
    v = np.arange(len(pidx)) - np.repeat(np.cumsum(counts) - counts, counts)
    W = look_at_batch(frames, positions[pidx], roll)
    _, nearest = tree.query(frames)
    in_sight = q.line_of_sight(frames, positions[pidx], tol)
    obl = obliqueness(normals[pidx], positions[pidx], frames)
    return ViewArrays(pidx, v, np.asarray(nearest, dtype=np.int64), W, fov, roll, obl, in_sight)
