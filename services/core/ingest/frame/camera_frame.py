"""Whether a scan is stored in an OpenCV camera's frame: its capture's (first) camera at the origin, looking
along +Z with the image's y down. Depth frames and RGB-D fusions are written so (7-Scenes, TUM, NYU, 3DMatch,
Kinect clouds), and a camera is held upright, so such a scan's up has a share of -Y (`up_evidence`'s
`camera_frame` term).

Frames and units: source frame and units; every test here is unit free.
- A camera's scan lies ahead of it: `AHEAD_SHARE` of it within `AHEAD_CONE_DEG` of +Z (a frame's view, and
  its neighbours' in a fused window). A randomly turned copy of the corpus' scans keeps that in 7-25 turns in
  100, so what this feeds is weighed as a habit (`up_evidence`).
- The scan fills much of the camera's view, not a few degrees of it (`single_view.seen_from_afar`).
- The origin sees the scan: at least `SEEN_RATIO` of the share of its points the centre of its bounding box
  along its principal axes sees (`visible_share`, `principal_box_centre`), so a frame moved off its camera (an
  origin under the floor) is not taken for one. On the real clouds of bench/ingest/ingest_real.py, camera
  origins see 1.01-5.4 times what the centre sees (a lidar's 10.8); origins that are no camera (a room's
  corner on its floor, a fragment moved by its registration, an edge cloud's world origin) 0.17-0.83 times. A
  phone session's start is a camera's place with the world's axes (Z or Y up): two of five ceiling captures
  pass, their floor family across -Y, which the term then leaves alone.
- `origin_is_camera` asks the same of a scan turned any way, its mean direction from the origin taken for
  +Z: where a cloud's normals face (services.core.ingest.pointcloud.viewpoint), which must not depend on how
  the file was turned. Measured so on the real clouds, in every turn of the bench: camera origins see
  0.93-4.5 times what the centre sees (a phone session's start and SUN RGB-D's gravity-turned frames among
  them; the least, the Redwood apartment's first 3,000 frames fused), the others 0.30-0.81.
"""

from __future__ import annotations

import numpy as np

from services.core.ingest.frame.single_view import seen_from_afar

VISIBLE_BIN_DEG = 2.0  # direction cells of `visible_share`: ~10 cm at 3 m, filled by a scan's 1-2 cm spacing
VISIBLE_DEPTH_TOLERANCE = 0.05
SAMPLE = 200_000  # points weighed at most
AHEAD_CONE_DEG = 60.0
AHEAD_SHARE = 0.8
SEEN_RATIO = 0.9


def visible_share(points: np.ndarray, eye: np.ndarray) -> float:
    """Share of `points` nearest to `eye` along their direction from it (within `VISIBLE_DEPTH_TOLERANCE`),
    directions binned in `VISIBLE_BIN_DEG` cells of azimuth and elevation: how much of the scan `eye` sees."""
    v = points - eye
    r = np.linalg.norm(v, axis=1)
    u = v / np.maximum(r, 1e-12)[:, None]
    n_az, n_el = int(360 / VISIBLE_BIN_DEG), int(180 / VISIBLE_BIN_DEG)
    az = ((np.arctan2(u[:, 1], u[:, 0]) + np.pi) / (2 * np.pi) * n_az).astype(int)
    el = ((np.arcsin(np.clip(u[:, 2], -1.0, 1.0)) + np.pi / 2) / np.pi * n_el).astype(int)
    cell = np.clip(el, 0, n_el - 1) * n_az + np.clip(az, 0, n_az - 1)
    nearest = np.full(n_az * n_el, np.inf)
    np.minimum.at(nearest, cell, r)
    return float(np.mean(r <= nearest[cell] * (1.0 + VISIBLE_DEPTH_TOLERANCE)))


def _sample(points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64)[:: max(1, len(points) // SAMPLE)]


def facing_z(direction: np.ndarray) -> np.ndarray:
    """A rotation taking the unit `direction` to +Z (any one: the turn about it is left free)."""
    d = direction / np.linalg.norm(direction)
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]
    x = np.cross(helper, d)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(d, x), d])


def origin_is_camera(points: np.ndarray) -> bool:
    """True where the origin is a camera's place for the scan, in whatever orientation the scan was turned:
    the test of `in_camera_frame` with the scan's mean direction from the origin taken for the camera's +Z."""
    sample = _sample(points)
    r = np.linalg.norm(sample, axis=1)
    mean_direction = (sample / np.maximum(r, 1e-12)[:, None]).mean(axis=0) if len(sample) else np.zeros(3)
    if np.linalg.norm(mean_direction) < 1e-9:
        return False
    return in_camera_frame(sample @ facing_z(mean_direction).T)


def in_camera_frame(points: np.ndarray) -> bool:
    """True for a scan stored in an OpenCV camera's frame (module docstring)."""
    sample = _sample(points)
    if len(sample) == 0 or seen_from_afar(sample):
        return False
    r = np.linalg.norm(sample, axis=1)
    if float(np.mean(sample[:, 2] > r * np.cos(np.radians(AHEAD_CONE_DEG)))) < AHEAD_SHARE:
        return False
    centre = principal_box_centre(sample)
    return visible_share(sample, np.zeros(3)) >= SEEN_RATIO * visible_share(sample, centre)


def principal_box_centre(points: np.ndarray) -> np.ndarray:
    """Centre of the scan's bounding box along its principal axes: the same place however the scan is turned
    (an axis-aligned box's centre moves with the turn, and a borderline origin passed in some turns only)."""
    mean = points.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((points - mean).T))
    along = (points - mean) @ axes
    return mean + axes @ (0.5 * (along.min(axis=0) + along.max(axis=0)))
