"""Path geometry of trajectory clips, and the motion limits a clip is held to (world metres, radians).

Resampling, trimming, frames at a spacing along a polyline, turn and rotation angles, and the adaptive
Gaussian smoothing of step 3 of services.scheduler.planning.trajectory (its docstring has the why).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from services.core.domain.jobspec import ViewSpec

ROLL_SHARE = 0.1  # of the view-rate limit that roll may use
DENSE_PER_FRAME = 2  # smoothing samples per frame spacing ...
MAX_SAMPLES_PER_RADIUS = 40  # ... or per smallest radius of curvature when frames are closer
SIGMA_GROWTH = 1.5
SMOOTHING_LEVELS = 9
FAIRING_MARGIN = 0.8  # smooth to this share of the limit: frames span several dense samples


def unit_vector(v: np.ndarray) -> np.ndarray:
    """`v` scaled to length 1 along its last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def resample(poly: np.ndarray, step: float, *, keep_end: bool = True) -> np.ndarray:
    """Points every `step` metres of arc along a polyline from its start; keep_end adds its end point
    after the last whole step (a shorter last step)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    if s[-1] <= 0:
        return poly[:1]
    targets = np.arange(int(np.floor(s[-1] / step + 1e-9)) + 1) * step
    if keep_end and s[-1] - targets[-1] > 1e-9:
        targets = np.append(targets, s[-1])
    return np.stack([np.interp(targets, s, poly[:, k]) for k in range(3)], axis=1)


def trim(poly: np.ndarray, length: float) -> np.ndarray:
    """The first `length` metres of a polyline (the whole of a shorter one)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    if s[-1] <= length:
        return poly
    k = int(np.searchsorted(s, length, side="right"))  # poly[:k] lies within the length
    t = (length - s[k - 1]) / (s[k] - s[k - 1])
    return np.vstack([poly[:k], poly[k - 1] + t * (poly[k] - poly[k - 1])])


def frames_along(dense: np.ndarray, spacing: float) -> np.ndarray:
    """Points every `spacing` metres along a smooth dense polyline, from its start: on a C2 cubic
    spline through the samples over their chord length, so frames closer than the samples still turn
    smoothly."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    if len(dense) < 3 or s[-1] <= 0:
        return resample(dense, spacing, keep_end=False)
    spline = CubicSpline(s, dense, bc_type="natural")
    return spline(np.arange(int(np.floor(s[-1] / spacing + 1e-9)) + 1) * spacing)


def turn_angles(pts: np.ndarray) -> np.ndarray:
    """(n-2,) radians between consecutive displacement vectors of a polyline."""
    d = np.diff(pts, axis=0)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return np.arccos(np.clip(np.einsum("ij,ij->i", d[:-1], d[1:]), -1.0, 1.0))


def rotation_angles(world_to_camera: np.ndarray) -> np.ndarray:
    """(n-1,) radians of the rotation between consecutive camera orientations."""
    R = world_to_camera[:, :3, :3]
    tr = np.einsum("nij,nij->n", R[:-1], R[1:])  # trace(R_a R_b^T)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def _gaussian(dense: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass along the samples (sigma in samples); the ends are mirrored by point reflection,
    so they stay put and the path runs straight on past them."""
    w = int(4.0 * sigma + 0.5) + 1  # the filter's reach
    padded = np.pad(dense, ((w, w), (0, 0)), mode="reflect", reflect_type="odd")
    return gaussian_filter1d(padded, sigma, axis=0, mode="nearest", truncate=4.0)[w:w + len(dense)]


def _curvature(pts: np.ndarray) -> np.ndarray:
    """(n,) turn per metre at each sample (0 at the ends): turn angle / mean of the adjacent steps."""
    out = np.zeros(len(pts))
    if len(pts) > 2:
        step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        out[1:-1] = turn_angles(pts) / np.maximum((step[:-1] + step[1:]) / 2, 1e-12)
    return out


def smooth_path(route: np.ndarray, spacing: float, max_turn_per_m: float) -> np.ndarray:
    """Dense points (every spacing / DENSE_PER_FRAME) of a smoothed route whose direction turns at most
    max_turn_per_m radians per metre wherever smoothing can make it so (module docstring, step 3).

    Adaptive bandwidth: Gaussian smoothings of growing sigma, and at each sample the least smoothing
    whose curvature within a radius of curvature is below the bound, blended with a smooth weight, so
    straight stretches keep their place (and clearance) and only sharp bends are rounded more. A
    reversal (cusp) cannot be rounded and is cut by the frame checks."""
    # dense enough for the frames and for the bends, but a bounded number of samples per bend
    h = max(spacing / DENSE_PER_FRAME, 1.0 / max_turn_per_m / MAX_SAMPLES_PER_RADIUS)
    dense = resample(route, h)
    if len(dense) < 3:
        return dense
    sigma0 = 0.15 / max_turn_per_m / h  # a small share of the smallest allowed radius of curvature, samples
    levels = np.stack([_gaussian(dense, sigma0 * SIGMA_GROWTH**k) for k in range(SMOOTHING_LEVELS)])
    reach = max(1, int(round(1.0 / max_turn_per_m / h)))
    need = np.full(len(dense), SMOOTHING_LEVELS - 1.0)
    for k in range(SMOOTHING_LEVELS - 1, -1, -1):
        ok = maximum_filter1d(_curvature(levels[k]), 2 * reach + 1) <= FAIRING_MARGIN * max_turn_per_m
        need[ok] = k
    # the level map itself varies slowly, so blending adds little curvature of its own; where the
    # blend is still too sharp, one more level everywhere
    level = gaussian_filter1d(maximum_filter1d(need, 6 * reach + 1), 3 * reach, mode="nearest")
    idx = np.arange(len(dense))
    for extra in range(SMOOTHING_LEVELS):
        at = np.clip(level + extra, 0, SMOOTHING_LEVELS - 1)
        lo = np.floor(at).astype(np.int64)
        hi = np.minimum(lo + 1, SMOOTHING_LEVELS - 1)
        t = (at - lo)[:, None]
        smooth = resample((1 - t) * levels[lo, idx] + t * levels[hi, idx], h)
        frames = frames_along(smooth, spacing)
        if len(frames) < 3 or turn_angles(frames).max() <= max_turn_per_m * spacing:
            break
    return smooth


def longest_run(good: np.ndarray, link: np.ndarray) -> tuple[int, int]:
    """[start, stop) of the longest run of good frames joined by good links (link[i]: frame i to i+1)."""
    best, start = (0, 0), 0
    for i in range(len(good)):
        if not good[i]:
            start = i + 1
            continue
        if i > start and not link[i - 1]:
            start = i
        if i + 1 - start > best[1] - best[0]:
            best = (start, i + 1)
    return best


@dataclass(frozen=True)
class Limits:
    """What every clip of a plan is held to (lengths in metres, rates in radians per metre)."""

    spacing: float
    turn_rate: float
    view_rate: float
    max_frames: int
    min_frames: int
    ahead: bool
    clearance: float
    tol: float  # line-of-sight tolerance to the point

    @classmethod
    def of(cls, spec: ViewSpec, clearance: float, tol: float, scale: float = 1.0) -> Limits:
        """The spec's limits, lengths multiplied by `scale` (object clips, module docstring step 6)."""
        view_rate = np.radians(spec.trajectory_max_view_deg_per_m) / scale
        turn_rate = np.radians(spec.trajectory_max_turn_deg_per_m) / scale
        ahead = spec.trajectory_look == "ahead"
        if ahead:  # the view follows the direction of motion
            turn_rate = min(turn_rate, (1.0 - ROLL_SHARE) * view_rate)
        return cls(
            spec.trajectory_spacing_m * scale, float(turn_rate), float(view_rate), spec.trajectory_max_frames,
            spec.trajectory_min_frames, ahead, clearance, tol,
        )
