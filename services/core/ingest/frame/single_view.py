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

# 98 % of the points this close to the mean direction: one view (a Kinect's half diagonal ~35)
VIEW_CONE_DEG = 36.0
# and no closer than this: a camera's scan fills much of its view (the corpus' camera-frame scans 32-70), so
# a scan that narrow from the origin lies far from it, where no depth camera stood (a phone session's start
# 2.7 scan diagonals away: 4)
MIN_VIEW_DEG = 15.0
LANDSCAPE_ASPECT = 1.15  # the frustum's wide axis over its short one: below it the frame's rows are not known
_SAMPLE = 20_000


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
