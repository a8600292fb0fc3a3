"""Loops and arcs for trajectory clips (step 2b of services.scheduler.planning.trajectory): level circles
round free space near a point, circles round the point itself, and orbits round an object. Their frames are
exact: no smoothing moves them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from services.scheduler.planning.paths import ROLL_SHARE, Limits, resample, unit_vector
from services.scheduler.planning.visibility import MeshQueries

LOOP_CANDIDATES = 8  # loop centres tried per point (rooms) ...
LOOP_PROBES = 16  # ... of those whose free radius, probed by this many level rays, is largest
LOOP_SHARE = 0.9  # of the limits a loop may use (its frames are exact: no smoothing moves them)
LOOP_RADIUS_GROWTH = 1.25  # loop radius: this x the smallest the turn limit allows, where the room allows
LOOP_HEIGHT_SWING = 0.15  # metres up and down: each lap at another height ...
LOOP_SWING_RATE = 0.37  # ... swinging this many cycles per radian of lap (no whole fraction: laps differ)
ARC_RADII = (1.05, 1.4, 1.8)  # circles round a point: radii in the least the limits allow
ORBIT_TILT_DEG = (42.0, 8.0)  # object orbits: angle between the axis and the camera, mean and swing


def spiral(
    base: np.ndarray, axis: np.ndarray, radius: Callable[[np.ndarray], np.ndarray],
    along: Callable[[np.ndarray], np.ndarray], lim: Limits, rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Frames every lim.spacing (at most lim.max_frames) of a loop around the line through `base` along
    `axis`: at lap angle phi (from a random start, either way round) the camera is radius(phi) from the
    line and along(phi) along it; and the points of the line the loop winds round (its anchors)."""
    axis = unit_vector(axis)
    u = unit_vector(np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0]))
    w = np.cross(axis, u)
    length = lim.spacing * (lim.max_frames - 1)
    probe = radius(np.linspace(0.0, 2 * np.pi / LOOP_SWING_RATE, 256))  # a whole swing
    r_lo, r_hi = float(probe.min()), float(probe.max())
    phi = np.arange(0.0, 1.5 * length / r_lo + 1e-9, lim.spacing / (8.0 * r_hi))
    start, sense = rng.uniform(0.0, 2 * np.pi), rng.choice([-1.0, 1.0])
    turn = start + sense * phi
    ring = np.cos(turn)[:, None] * u + np.sin(turn)[:, None] * w
    dense = base + along(phi)[:, None] * axis + radius(phi)[:, None] * ring
    return resample(dense, lim.spacing, keep_end=False)[:lim.max_frames], base + along(phi)[::8, None] * axis


def room_loops(
    point: np.ndarray, cams: np.ndarray, lim: Limits, q: MeshQueries, rng: np.random.Generator,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Level loops round the cameras with the most free space about them, far enough from the point that
    the view turns slowly where the loop passes it (module docstring, step 2b)."""
    # the view turns 1 / distance per metre moved sideways; the radius of a circle is its turn per metre
    near_pass = 0.0 if lim.ahead else 1.0 / (LOOP_SHARE * (1.0 - ROLL_SHARE) * lim.view_rate)
    tight = 1.0 / (LOOP_SHARE * lim.turn_rate)
    reach = np.linalg.norm((cams - point)[:, :2], axis=1) - near_pass
    ok = np.flatnonzero(reach >= tight)
    if not len(ok):
        return []
    # free radius: the nearest wall along LOOP_PROBES level rays, less a margin for the clearance
    angle = np.arange(LOOP_PROBES) * 2 * np.pi / LOOP_PROBES
    dirs = np.stack([np.cos(angle), np.sin(angle), np.zeros(LOOP_PROBES)], axis=1)
    hit, _ = q.first_hit(np.repeat(cams[ok], LOOP_PROBES, axis=0), np.tile(dirs, (len(ok), 1)))
    free = hit.reshape(len(ok), LOOP_PROBES).min(axis=1) - 2 * lim.clearance
    radius = np.minimum(np.minimum(reach[ok], free), LOOP_RADIUS_GROWTH * tight)
    best = np.argsort(-radius, kind="stable")[:LOOP_CANDIDATES]
    # each centre with its widest loop and its tightest (less often hidden by furniture in part)
    loops = [
        (ok[i], r)
        for i in best
        if radius[i] >= tight
        for r in sorted({float(radius[i]), tight}, reverse=True)
    ]
    up = np.array([0.0, 0.0, 1.0])
    return [spiral(cams[c], up, _constant(r), _height_swing, lim, rng) for c, r in loops]


def point_arcs(
    point: np.ndarray, cams: np.ndarray, lim: Limits, rng: np.random.Generator
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Level circles round the point itself at the cameras' median height (module docstring, step 2b):
    where the room allows no loop in front of a point, the arc of such a circle that stays in the room
    and in sight is often longer than a route; the cameras that see the point are its anchors."""
    if not len(cams):
        return []
    base = np.array([point[0], point[1], float(np.median(cams[:, 2]))])
    nearest = max(1.0 / (LOOP_SHARE * (1.0 - ROLL_SHARE) * lim.view_rate), 1.0 / (LOOP_SHARE * lim.turn_rate))
    out = []
    for growth in ARC_RADII:
        frames, _ = spiral(
            base, np.array([0.0, 0.0, 1.0]), _constant(growth * nearest), _height_swing, lim, rng
        )
        out.append((frames, cams))
    return out


def _constant(value: float) -> Callable[[np.ndarray], np.ndarray]:
    def at(phi: np.ndarray) -> np.ndarray:
        return np.full(len(phi), value)
    return at


def _height_swing(phi: np.ndarray) -> np.ndarray:
    return LOOP_HEIGHT_SWING * np.sin(LOOP_SWING_RATE * phi)


def object_orbits(
    point: np.ndarray, normal: np.ndarray, cams: np.ndarray, distance: float, lim: Limits,
    rng: np.random.Generator,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Orbits `distance` from the point round an axis through it (its normal; the mean direction to the
    cameras that see it; up), tilted ORBIT_TILT_DEG from the axis with a slow swing (module docstring, 2b)."""
    mean_tilt, swing = np.radians(ORBIT_TILT_DEG)
    # and up: a steep axis would carry the camera over the point, where looking down spins the view
    axes = (
        [normal]
        + ([unit_vector(unit_vector(cams - point).mean(axis=0))] if len(cams) else [])
        + [np.array([0.0, 0.0, 1.0])]
    )

    def tilt(phi: np.ndarray) -> np.ndarray:
        return mean_tilt + swing * np.sin(LOOP_SWING_RATE * phi)

    def off_axis(phi: np.ndarray) -> np.ndarray:
        return distance * np.sin(tilt(phi))

    def along_axis(phi: np.ndarray) -> np.ndarray:
        return distance * np.cos(tilt(phi))

    return [spiral(point, a, off_axis, along_axis, lim, rng) for a in axes]
