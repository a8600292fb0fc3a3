"""A scan seen from one place: a single depth frame (or a few taken from one spot), stored in its camera's
frame.

Frames and units: the source frame, any unit. A depth frame back-projected into its camera's frame (and later
rotated or scaled about that frame's origin, as exports do) has the camera at the source origin, and every
point lies in the camera's frustum: a narrow cone about the view direction, wider across the image's rows than
down its columns (depth cameras are held in landscape). Up then lies across the view direction within the
camera's pitch, close to the frustum's short axis. Room-scale evidence (a room wider than tall) measures the
frustum instead of the room in such a scan, so `up_evidence` scores a single view by these instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# 98 % of the points this close to the mean direction: one view (a Kinect's half diagonal ~35)
VIEW_CONE_DEG = 36.0
# and no closer than this: a camera's scan fills much of its view (the corpus' camera-frame scans 32-70), so
# a scan that narrow from the origin lies far from it, where no depth camera stood (a phone session's start
# 2.7 scan diagonals away: 4)
MIN_VIEW_DEG = 15.0
LANDSCAPE_ASPECT = 1.15  # the frustum's wide axis over its short one: below it the frame's rows are not known
_SAMPLE = 20_000
# A depth frame holds one depth per ray, so from the origin nothing lies behind anything but at depth
# edges: on the real frames of bench/ingest/ingest_real.py 0.1-2.1 % of the points have a point 5 % nearer
# within twice the points' median angular spacing; a fusion of several views holds what its other cameras
# saw behind (3.2-45 % on its fused fragments, several of them as narrow as one view)
OCCLUDED_MAX_SHARE = 0.025
_OCCLUSION_SAMPLE = 60_000
_OCCLUSION_NEIGHBOURS = 8
_OCCLUSION_NEARER = 0.05


@dataclass(frozen=True)
class SingleView:
    """Where a single view looked (unit vector, source frame) and the frame's short axis across it, if
    known."""

    direction: np.ndarray
    short_axis: np.ndarray | None


def _directions(vertices: np.ndarray) -> np.ndarray | None:
    """Unit directions from the source origin to (a sample of) the vertices; None for fewer than 100."""
    v = np.asarray(vertices, dtype=np.float64)
    v = v[:: len(v) // _SAMPLE + 1]
    norms = np.linalg.norm(v, axis=1)
    v, norms = v[norms > 0], norms[norms > 0]
    return None if len(v) < 100 else v / norms[:, None]


def _seen_from_origin(vertices: np.ndarray) -> np.ndarray | None:
    """The mean direction (unit) from the source origin to the scan, when the scan lies on one side of the
    origin (a capture stored in its first camera's frame: that camera stood there, looking along +Z); None
    when the scan surrounds the origin or lies every way from it."""
    d = _directions(vertices)
    if d is None:
        return None
    mean = d.mean(axis=0)
    n = float(np.linalg.norm(mean))
    return None if n < 0.5 else mean / n


def _spread_deg(d: np.ndarray, mean: np.ndarray) -> float:
    """How far from the mean direction the scan reaches, degrees (98 % of it)."""
    return float(np.percentile(np.degrees(np.arccos(np.clip(d @ mean, -1.0, 1.0))), 98))


def seen_from_afar(vertices: np.ndarray) -> bool:
    """True when the scan lies within `MIN_VIEW_DEG` of one direction from the source origin: no camera at
    the origin took it."""
    d = _directions(vertices)
    mean = None if d is None else _seen_from_origin(vertices)
    return d is not None and mean is not None and _spread_deg(d, mean) < MIN_VIEW_DEG


def occluded_share(points: np.ndarray) -> float:
    """Share of (a sample of) `points` with another point `_OCCLUSION_NEARER` nearer the origin in about the
    same direction (among its nearest directions, within twice the median spacing between directions)."""
    p = np.asarray(points, dtype=np.float64)
    p = p[:: max(1, len(p) // _OCCLUSION_SAMPLE)]
    r = np.linalg.norm(p, axis=1)
    p, r = p[r > 0], r[r > 0]
    if len(p) <= _OCCLUSION_NEIGHBOURS:
        return 0.0
    spacing, nearest = cKDTree(p / r[:, None]).query(p / r[:, None], k=_OCCLUSION_NEIGHBOURS + 1)
    close = spacing[:, 1:] <= 2.0 * float(np.median(spacing[:, 1]))
    nearer = r[nearest[:, 1:]] < (1.0 - _OCCLUSION_NEARER) * r[:, None]
    return float((close & nearer).any(axis=1).mean())


def frame_view(points: np.ndarray) -> SingleView | None:
    """The view of a point cloud's own points when they are one depth frame: one camera's frustum
    (`single_view`) and none of them behind another (`occluded_share`: a fusion of several views can be as
    narrow), else None."""
    view = single_view(points)
    return view if view is not None and occluded_share(points) <= OCCLUDED_MAX_SHARE else None


def single_view(vertices: np.ndarray) -> SingleView | None:
    """The view of a scan whose points all lie in one camera's frustum at the source origin, else None."""
    d = _directions(vertices)
    mean = None if d is None else _seen_from_origin(vertices)
    if d is None or mean is None:
        return None
    if not MIN_VIEW_DEG <= _spread_deg(d, mean) <= VIEW_CONE_DEG:
        return None
    across = d - np.outer(d @ mean, mean)
    # ascending: ~0 along the view, short axis, wide axis
    values, vectors = np.linalg.eigh(across.T @ across)
    landscape = values[1] > 0 and np.sqrt(values[2] / values[1]) >= LANDSCAPE_ASPECT
    return SingleView(mean, vectors[:, 1] if landscape else None)
