"""Fixated views (world metres, radians; world_to_camera into OpenCV axes, see services.core.domain.camera).

wide_baseline: one view per camera-point pair with line of sight; when a point is seen by more than
max_views cameras, max_views of them are chosen by the rng. Each view looks from the camera straight
at the point (the point projects to the image centre), with
  fov ~ normal(fov_mean, fov_std) truncated to [fov_min, fov_max] (inverse-CDF sampling),
  roll ~ U[-roll_max, roll_max] about the optical axis, relative to gravity (camera.look_at),
  obliqueness = angle between the point normal and the direction from the point to the camera.

nonfixated_pruning: a view is kept only when its camera also sees (line of sight, inside the image)
another point that has at least two views, so every kept view carries a cross-view correspondence;
one pass over the unpruned view counts. Points left with fewer than min_views views are then dropped.
A trajectory clip keeps only its longest run of kept frames (at least trajectory_min_frames), so that
no frame is missing inside a clip; this applies to min_valid_fraction below too.

valid fraction (holes in scans): each view's share of pixels that see a surface is predicted by a
8 x 8 ray cast; views.min_valid_fraction drops views below it (points then as above).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from services.core.domain.camera import intrinsics
from services.core.domain.jobspec import ViewSpec
from services.core.domain.plan import ValidFractionSummary
from services.scheduler.planning.visibility import MeshQueries


@dataclass(frozen=True)
class ViewArrays:
    """Views as parallel arrays, sorted by (point_idx, v)."""

    point_idx: np.ndarray  # (n,) int
    v: np.ndarray  # (n,) int, 0..k-1 within each point
    camera_idx: np.ndarray  # (n,) int
    world_to_camera: np.ndarray  # (n, 4, 4)
    fov: np.ndarray  # (n,) radians
    roll: np.ndarray  # (n,) radians
    obliqueness: np.ndarray  # (n,) radians
    in_sight: np.ndarray  # (n,) bool

    def __len__(self) -> int:
        return len(self.point_idx)

    def subset(self, keep: np.ndarray) -> ViewArrays:
        """The views where `keep` is true (v is not renumbered)."""
        return ViewArrays(*(getattr(self, f)[keep] for f in self.__dataclass_fields__))


def truncated_normal(
    rng: np.random.Generator, mean: float, std: float, lo: float, hi: float, size: int
) -> np.ndarray:
    """Samples of normal(mean, std) truncated to [lo, hi] by inverse-CDF (one uniform per sample)."""
    u = rng.random(size)
    if std <= 0:
        return np.full(size, float(np.clip(mean, lo, hi)))
    a, b = (lo - mean) / std, (hi - mean) / std
    if a > 0:  # deep in the upper tail: mirror to the lower tail where ndtr keeps its precision
        x = -ndtri(ndtr(-b) + u * (ndtr(-a) - ndtr(-b)))
    else:
        x = ndtri(ndtr(a) + u * (ndtr(b) - ndtr(a)))
    return np.clip(mean + std * x, lo, hi)


def quantile_sample(rng: np.random.Generator, quantiles: Sequence[float], size: int) -> np.ndarray:
    """Samples of the distribution with these quantiles at equally spaced levels 0..1 (piecewise-linear
    inverse CDF, one uniform per sample)."""
    q = np.asarray(quantiles, dtype=np.float64)
    return np.interp(rng.random(size), np.linspace(0.0, 1.0, len(q)), q)


def sample_fov(rng: np.random.Generator, spec: ViewSpec, size: int) -> np.ndarray:
    """(size,) fields of view in radians: the truncated normal, or fov_quantiles_deg when given."""
    if spec.fov_quantiles_deg is not None:
        return np.radians(quantile_sample(rng, spec.fov_quantiles_deg, size))
    return truncated_normal(
        rng, np.radians(spec.fov_mean_deg), np.radians(spec.fov_std_deg),
        np.radians(spec.fov_min_deg), np.radians(spec.fov_max_deg), size,
    )


def sample_roll(rng: np.random.Generator, spec: ViewSpec, size: int) -> np.ndarray:
    """(size,) rolls in radians: uniform in [-roll_max, roll_max], or roll_quantiles_deg when given."""
    if spec.roll_quantiles_deg is not None:
        return np.radians(quantile_sample(rng, spec.roll_quantiles_deg, size))
    rmax = np.radians(spec.roll_max_deg)
    return rng.uniform(-rmax, rmax, size)


def pitch_deg(cameras: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Pitch in degrees (+ up: the optical axis above the horizontal) of views fixated on targets."""
    d = targets - cameras
    return np.degrees(np.arctan2(d[:, 2], np.linalg.norm(d[:, :2], axis=1)))


def pitch_acceptance(pitch: np.ndarray, quantiles: Sequence[float]) -> np.ndarray:
    """Per candidate, the probability of keeping it so that the kept pitches follow the quantiles: in each bin
    between consecutive quantiles, the target's share over the candidates' share, scaled so the largest is 1.
    Bins no candidate falls in cannot be reached and are left out (the rest keep their proportions)."""
    q = np.asarray(quantiles, dtype=np.float64)
    edges, first = np.unique(q, return_index=True)
    levels = np.linspace(0.0, 1.0, len(q))
    if len(edges) == 1:  # a point mass: the candidates within half a degree of it
        return (np.abs(pitch - edges[0]) <= 0.5).astype(np.float64)
    # the level of each distinct edge is its last occurrence (a run of equal quantiles is a jump of the CDF)
    last = np.r_[first[1:] - 1, len(q) - 1]
    target = np.diff(levels[last])
    target[0] += levels[last[0]]  # mass at the lowest edge (a jump there) goes to the first bin
    b = np.searchsorted(edges, pitch, side="right") - 1
    b[pitch == edges[-1]] = len(edges) - 2
    inside = (b >= 0) & (b < len(edges) - 1)
    have = np.bincount(b[inside], minlength=len(edges) - 1) / max(len(pitch), 1)
    ratio = np.where(have > 0, target / np.maximum(have, 1e-300), 0.0)
    accept = np.zeros(len(pitch))
    if ratio.max() > 0:
        accept[inside] = ratio[b[inside]] / ratio.max()
    return accept


def look_at_batch(positions: np.ndarray, targets: np.ndarray, rolls: np.ndarray) -> np.ndarray:
    """(n, 4, 4) world_to_camera, the vectorised twin of services.core.domain.camera.look_at (same result)."""
    positions = np.asarray(positions, dtype=np.float64)
    z = np.asarray(targets, dtype=np.float64) - positions
    norm = np.linalg.norm(z, axis=1, keepdims=True)
    if (norm == 0).any():
        raise ValueError("camera position and target coincide")
    z = z / norm
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    flat = np.linalg.norm(x, axis=1) < 1e-9
    if flat.any():
        x[flat] = np.cross(z[flat], np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    c, s = np.cos(rolls)[:, None], np.sin(rolls)[:, None]
    x, y = c * x + s * y, -s * x + c * y
    W = np.zeros((len(positions), 4, 4))
    W[:, 0, :3], W[:, 1, :3], W[:, 2, :3] = x, y, z
    W[:, :3, 3] = -np.einsum("nij,nj->ni", W[:, :3, :3], positions)
    W[:, 3, 3] = 1.0
    return W


def obliqueness(normals: np.ndarray, points: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """Angles (radians) between point normals and the directions from the points to the cameras."""
    d = cameras - points
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("ij,ij->i", normals, d), -1.0, 1.0))


def cap_views(
    cams: Sequence[int] | np.ndarray, max_views: int | None, rng: np.random.Generator
) -> np.ndarray:
    """The cameras of a point, at most max_views of them chosen by rng (kept in index order)."""
    cams = np.asarray(cams, dtype=np.int64)
    if max_views is not None and len(cams) > max_views:
        cams = np.sort(rng.choice(cams, size=max_views, replace=False))
    return cams


def wide_baseline(
    positions: np.ndarray,
    normals: np.ndarray,
    visible: tuple[np.ndarray, ...],
    cameras: np.ndarray,
    spec: ViewSpec,
    max_views: int | None,
    rng: np.random.Generator,
    min_views: int = 1,
) -> ViewArrays:
    """One fixated view per visible camera-point pair (at most max_views per point, chosen by rng); with
    views.pitch_quantiles_deg, of the pairs thinned by pitch (a point left with < min_views gets none)."""
    if spec.pitch_quantiles_deg is not None:
        visible = thin_by_pitch(positions, visible, cameras, spec.pitch_quantiles_deg, min_views, rng)
    return wide_baseline_span(positions, normals, visible, cameras, spec, max_views, (0, len(visible)),
                              (rng, rng, rng))


def wide_baseline_span(
    positions: np.ndarray,
    normals: np.ndarray,
    visible: tuple[np.ndarray, ...],
    cameras: np.ndarray,
    spec: ViewSpec,
    max_views: int | None,
    span: tuple[int, int],
    rngs: tuple[np.random.Generator, np.random.Generator, np.random.Generator],
) -> ViewArrays:
    """wide_baseline's views of points span[0]..span[1]-1; rngs = (camera choices, fovs, rolls).

    One generator three times draws all choices, then all fovs, then all rolls: the whole plan's order, which
    a chunk reproduces from copies of the generator advanced to its first draw of each kind.
    """
    choice_rng, fov_rng, roll_rng = rngs
    lo, hi = span
    chosen = [cap_views(visible[p], max_views, choice_rng) for p in range(lo, hi)]
    P = np.repeat(np.arange(lo, hi, dtype=np.int64), [len(c) for c in chosen])
    none = np.zeros(0, dtype=np.int64)
    C = np.concatenate(chosen) if chosen else none
    V = np.concatenate([np.arange(len(c), dtype=np.int64) for c in chosen]) if chosen else none
    n = len(P)
    fov = sample_fov(fov_rng, spec, n)
    roll = sample_roll(roll_rng, spec, n)
    W = look_at_batch(cameras[C], positions[P], roll) if n else np.zeros((0, 4, 4))
    obl = obliqueness(normals[P], positions[P], cameras[C]) if n else np.zeros(0)
    return ViewArrays(P, V, C, W, fov, roll, obl, np.ones(n, dtype=bool))


def thin_by_pitch(
    positions: np.ndarray, visible: tuple[np.ndarray, ...], cameras: np.ndarray, quantiles: Sequence[float],
    min_views: int, rng: np.random.Generator,
) -> tuple[np.ndarray, ...]:
    """The cameras of each point kept by pitch_acceptance (one uniform per pair); none if < min_views stay."""
    if not visible:
        return visible
    counts = np.array([len(c) for c in visible], dtype=np.int64)
    C = np.concatenate(visible).astype(np.int64)
    P = np.repeat(np.arange(len(visible)), counts)
    keep = rng.random(len(C)) < pitch_acceptance(pitch_deg(cameras[C], positions[P]), quantiles)
    parts = np.split(keep, np.cumsum(counts)[:-1])
    kept = tuple(np.asarray(c, dtype=np.int64)[k] for c, k in zip(visible, parts, strict=True))
    return tuple(c if len(c) >= min_views else c[:0] for c in kept)


def nonfixated_keep(
    views: ViewArrays, positions: np.ndarray, visible: tuple[np.ndarray, ...], resolution: int
) -> np.ndarray:
    """(n_views,) bool: the view's camera sees another point with >= 2 views inside the image."""
    n_views = np.bincount(views.point_idx, minlength=len(positions))
    seen_by: dict[int, list[int]] = {}
    for p, cams in enumerate(visible):
        if n_views[p] >= 2:
            for c in cams:
                seen_by.setdefault(int(c), []).append(p)
    keep = np.zeros(len(views), dtype=bool)
    for i in range(len(views)):
        cand = np.array(seen_by.get(int(views.camera_idx[i]), []), dtype=np.int64)
        cand = cand[cand != views.point_idx[i]]
        if len(cand) == 0:
            continue
        W = views.world_to_camera[i]
        cam = positions[cand] @ W[:3, :3].T + W[:3, 3]
        front = cam[:, 2] > 0
        if not front.any():
            continue
        K = intrinsics(float(views.fov[i]), resolution)
        uv = cam[front, :2] / cam[front, 2:3] * K[0, 0] + K[:2, 2]
        keep[i] = bool(((uv >= 0) & (uv < resolution)).all(axis=1).any())
    return keep


# rays per side of the low-resolution cast that predicts a view's share of surface (64 rays)
VALID_PROBE_PX = 8


def valid_fractions(
    q: MeshQueries, views: ViewArrays, max_depth_m: float, size: int = VALID_PROBE_PX
) -> np.ndarray:
    """(n,) predicted share of each view's pixels that see a surface nearer than `max_depth_m` (z-depth,
    metres), from a `size` x `size` ray cast through pixel centres (the cue `mask_valid` at low
    resolution)."""
    n = len(views)
    if not n:
        return np.zeros(0)
    # pixel centres in units of the half-width: camera ray (g_x tan(fov/2), g_y tan(fov/2), 1), as
    # camera.pixel_rays
    g = (np.arange(size) + 0.5) / (size / 2) - 1.0
    gx, gy = np.meshgrid(g, g)
    t = np.tan(views.fov / 2)[:, None]
    d_cam = np.stack([gx.ravel() * t, gy.ravel() * t, np.ones((n, size * size))], axis=-1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    R = views.world_to_camera[:, :3, :3]
    dirs = np.einsum("npc,ncw->npw", d_cam, R)  # R^T d per view
    centres = -np.einsum("ncw,nc->nw", R, views.world_to_camera[:, :3, 3])
    origins = np.repeat(centres, size * size, axis=0)
    dist, _ = q.first_hit(origins, dirs.reshape(-1, 3))
    valid = np.isfinite(dist) & (dist * d_cam[..., 2].ravel() < max_depth_m)
    return valid.reshape(n, size * size).mean(axis=1)


def fraction_summary(fractions: np.ndarray, threshold: float) -> ValidFractionSummary:
    """The distribution of predicted valid fractions (job.json): quantiles, and how many fall below
    `threshold`."""
    if not len(fractions):
        return {"views": 0, "threshold": threshold, "dropped": 0}
    q = np.quantile(fractions, [0.0, 0.05, 0.25, 0.5, 0.75, 1.0])
    return {
        "views": int(len(fractions)), "threshold": threshold, "probe_px": VALID_PROBE_PX,
        "min": float(q[0]), "p05": float(q[1]), "p25": float(q[2]), "median": float(q[3]), "p75": float(q[4]),
        "max": float(q[5]), "mean": float(fractions.mean()),
        "dropped": int((fractions < threshold).sum()) if threshold > 0 else 0,
    }
