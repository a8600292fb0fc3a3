"""Trajectory views: per point a clip a camera could fly, smooth, in free space, at the spec's spacing.

World metres, radians; world_to_camera into OpenCV axes (services.core.domain.camera). Once per plan:
  1. free-space graph: the cameras (all in free space, clear of the mesh) are the nodes; an edge joins
     two cameras closer than EDGE_REACH x the median nearest-camera distance (or among each other's
     EDGE_KNN nearest) when nothing blocks the segment and samples along it every <= clearance/2 keep
     the clearance to the mesh; its weight is its length.
For each point:
  2. route: the cameras that see the point, and for fixated clips only the edges whose middle sees it
     and along which the view turns at most the view limit (point_graph: moving sideways close to
     the point turns the view fast, moving towards it does not). The first waypoint is chosen by the
     rng among cameras at least 1 / view rate from the point; each next one ends the best leg, a
     shortest path in that graph: long (up to LEG camera spacings straight-line, within the budget
     trajectory_spacing_m x (trajectory_max_frames - 1) plus BUDGET_MARGIN for cuts), away from
     the point, heading straight on (within 90 degrees of the last leg, LEAD spacings along it; no
     turn sharper than MAX_NODE_TURN at a camera: a reversal cannot be smoothed), at least
     WAYPOINT_SEP spacings from the earlier waypoints, and not at a dead end of the graph. The route
     grows forwards, then backwards from the first waypoint, while the budget lasts.
  2b. loops and arcs, besides the route (the longest verified clip of a point wins, the route on
     ties): level circles (the widest allowed and the tightest) round the LOOP_CANDIDATES cameras that
     see the point with the most free space about them (nearest wall along LOOP_PROBES level rays), of
     radius at least the turn limit's smallest (1 / (LOOP_SHARE x turn rate)), at most
     LOOP_RADIUS_GROWTH x that, passing the point no nearer than 1 / (LOOP_SHARE x the look's share of
     the view rate) (where a loop passes nearest it moves sideways, and the view turns 1 / distance
     per metre), each lap at another height (LOOP_HEIGHT_SWING) so the laps of a long clip differ; and
     level circles round the point itself at the cameras' median height, ARC_RADII x the least radius
     both limits allow, of which verification keeps the longest arc in the room and in sight. Their
     frames are exact: no smoothing.
  3. smoothing (approximating, not through the cameras): the route is resampled every spacing / 2 (at
     most MAX_SAMPLES_PER_RADIUS per smallest radius of curvature) and filtered by Gaussians of
     growing sigma along its arc (ends mirrored by point reflection, so they stay put); at each sample
     the least sigma whose curvature nearby is within FAIRING_MARGIN x trajectory_max_turn_deg_per_m
     is used, blended by a slowly varying weight, so straight stretches keep their place (and
     clearance) and only sharp bends are rounded more.
  4. frames every trajectory_spacing_m along the smoothed arc; frames nearer the mesh than the clearance
     are first pushed out along the distance gradient (from the nearest surface point) to PUSH_MARGIN x
     the clearance, by a bump as wide as the smallest radius of curvature (so the turn stays bounded),
     and the path resampled (PUSH_ROUNDS times at most); then each frame is verified: clearance >=
     cameras.clearance_m (exact distance; lowered to what the cameras themselves keep for provided or
     object cameras, attainable_clearance), a clear segment to the nearest anchor (a camera of the
     route, a point of a loop's axis) and to the previous frame (still inside the free space the
     cameras are in), the point in sight (fixated clips), the turn
     of the direction of motion and the camera rotation to the next frame within the limits. The clip
     is the longest run of frames that pass, at most trajectory_max_frames (the path is shortened,
     the spacing never stretched); a clip cut by a check is reported with the counts of failed checks,
     and one shorter than trajectory_min_frames (cut, or its route too short) is dropped.
  5. view: look: point fixates the point (the point projects to the image centre); look: ahead looks
     along the path's tangent (the turn bound then also keeps the view rate). Roll goes from one
     U[-roll_max, roll_max] draw to another along a smoothstep, its rate at most ROLL_SHARE of the
     view limit (the remaining share bounds the look direction); the fov is one truncated-normal draw
     per clip (a constant zoom). camera_idx = the nearest camera to the frame.
  6. objects (cameras.mode object, cameras on a sphere of radius r round the object): per-metre limits
     fixed for rooms would leave a small object no clip at all, so its clips are planned as if the
     sphere had a radius of OBJECT_REFERENCE_M: the spacing is trajectory_spacing_m x r /
     OBJECT_REFERENCE_M and the per-metre limits are divided by that factor (the per-frame figures, and
     the frame count, are those of a room). The clip orbits the point at distance r round an axis through
     it (its normal, the mean direction to the cameras that see it, or up: the longest verified clip
     wins), ORBIT_TILT_DEG from the axis with a slow swing, so laps differ.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.spatial import cKDTree
from scipy.special import erf

from services.core.domain.jobspec import ViewSpec
from services.core.domain.plan import ClipNoteRecord
from services.scheduler.planning.loops import object_orbits, point_arcs, room_loops
from services.scheduler.planning.paths import (
    ROLL_SHARE,
    Limits,
    frames_along,
    longest_run,
    resample,
    rotation_angles,
    smooth_path,
    trim,
    turn_angles,
)
from services.scheduler.planning.routes import (
    attainable_clearance,
    camera_spacing,
    choose_route,
    free_space_graph,
    point_graph,
)
from services.scheduler.planning.views import (
    ViewArrays,
    cap_views,
    look_at_batch,
    obliqueness,
    sample_fov,
    sample_roll,
)
from services.scheduler.planning.visibility import MeshQueries

BUDGET_MARGIN = 1.25  # route this much longer than the clip: verification may cut some of it
ROUTE_VIEW_SHARE = 0.75  # of the view-rate limit that route edges may need: smoothing moves the path
LIMIT_SLACK = 1.0 + 1e-6
PUSH_MARGIN = 1.05  # frames too near the mesh are pushed to this x the clearance ...
PUSH_ROUNDS = 3  # ... at most this many times (a push can bring a neighbour near)
DENSE_PER_PUSH = 8  # spline samples per frame spacing when a pushed path is resampled
OBJECT_REFERENCE_M = 5.0  # object clips are planned as if their camera sphere had this radius (step 6)


@dataclass
class ClipNote:
    """Why a point's clip is shorter than planned (or missing): sampled point index, frames kept and
    planned, and how many frames failed each check (keys of services.core.domain.plan.CLIP_CHECKS)."""

    point: int
    frames: int
    planned: int
    reasons: dict[str, int] = field(default_factory=dict)

    def as_dict(self, point_idx: int | None) -> ClipNoteRecord:
        """The JSON form, naming the point by its index in the plan (None: not in the plan)."""
        return {
            "point_idx": point_idx,
            "outcome": "dropped" if self.frames == 0 or point_idx is None else "shortened",
            "frames": self.frames, "planned_frames": self.planned,
            "reasons": dict(sorted(self.reasons.items())),
        }


@dataclass
class Clip:
    """One point's clip: frame positions (world metres), look-at targets, roll (radians), and the note
    when it was cut short or dropped."""

    frames: np.ndarray  # (n, 3)
    look: np.ndarray  # (n, 3) targets
    roll: np.ndarray
    note: ClipNote | None


def trajectory(
    positions: np.ndarray,
    normals: np.ndarray,
    visible: tuple[np.ndarray, ...],
    cameras: np.ndarray,
    spec: ViewSpec,
    max_views: int | None,
    q: MeshQueries,
    tol: float,
    clearance: float,
    rng: np.random.Generator,
    orbit: tuple[np.ndarray, float] | None = None,
) -> tuple[ViewArrays, list[ClipNote]]:
    """Frames of one clip per point (module docstring) and notes on the clips cut short or dropped;
    v numbers the frames of a point. orbit: (centre, radius m) of an object's camera sphere (cameras.mode
    object): clips orbit the point, their lengths scaled by radius / OBJECT_REFERENCE_M."""
    clearance = attainable_clearance(cameras, q, clearance)
    lim = Limits.of(spec, clearance, tol, orbit[1] / OBJECT_REFERENCE_M if orbit is not None else 1.0)
    budget = BUDGET_MARGIN * lim.spacing * (lim.max_frames - 1)
    graph = (
        free_space_graph(cameras, q, clearance) if orbit is None else sparse.csr_matrix((len(cameras),) * 2)
    )
    unit = camera_spacing(cameras)
    tree = cKDTree(cameras)
    P: list[np.ndarray] = []
    F: list[np.ndarray] = []
    T: list[np.ndarray] = []
    R: list[np.ndarray] = []
    FOV: list[np.ndarray] = []
    notes: list[ClipNote] = []
    for p, cams in enumerate(visible):
        cams = cap_views(cams, max_views, rng)
        roll_pair = sample_roll(rng, spec, 2)
        fov = float(sample_fov(rng, spec, 1)[0])
        clips: list[Clip] = []
        if orbit is not None:
            loops = object_orbits(positions[p], normals[p], cameras[cams], orbit[1], lim, rng)
        else:
            sub = graph[cams][:, cams]
            if not lim.ahead:
                sub = point_graph(sub, cameras[cams], positions[p], ROUTE_VIEW_SHARE * lim.view_rate, q, tol)
            node = choose_route(sub, cameras[cams], positions[p], budget, 1.0 / lim.view_rate, unit, rng)
            clips.append(fly_clip(cameras[cams][node], positions[p], lim, q, roll_pair, p))
            loops = room_loops(positions[p], cameras[cams], lim, q, rng) + point_arcs(
                positions[p], cameras[cams], lim, rng
            )
        clips += [
            verify_clip(frames, anchors, positions[p], lim, q, roll_pair, p) for frames, anchors in loops
        ]
        clip = max(clips, key=lambda c: len(c.frames))  # the first of the longest
        if clip.note is not None:
            notes.append(clip.note)
        n = len(clip.frames)
        P.append(np.full(n, p, dtype=np.int64))
        F.append(clip.frames)
        T.append(clip.look)
        R.append(clip.roll)
        FOV.append(np.full(n, fov))
    return _view_arrays(P, F, T, R, FOV, len(visible), positions, normals, tree, q, tol), notes


def _view_arrays(
    P: list[np.ndarray], F: list[np.ndarray], T: list[np.ndarray], R: list[np.ndarray], FOV: list[np.ndarray],
    n_points: int, positions: np.ndarray, normals: np.ndarray, tree: cKDTree, q: MeshQueries, tol: float,
) -> ViewArrays:
    """The clips' frames (per point: point index, positions, look targets, roll, fov) as the plan's views;
    v numbers the frames of a point, camera_idx is the nearest camera."""
    pidx = np.concatenate(P) if P else np.zeros(0, dtype=np.int64)
    if not len(pidx):
        z = np.zeros(0)
        return ViewArrays(z.astype(np.int64), z.astype(np.int64), z.astype(np.int64), np.zeros((0, 4, 4)),
                          z, z, z, z.astype(bool))
    frames = np.concatenate(F)
    roll = np.concatenate(R)
    fov_all = np.concatenate(FOV)
    counts = np.bincount(pidx, minlength=n_points)
    v = np.arange(len(pidx)) - np.repeat(np.cumsum(counts) - counts, counts)
    W = look_at_batch(frames, np.concatenate(T), roll)
    _, nearest = tree.query(frames)
    in_sight = q.line_of_sight(frames, positions[pidx], tol)
    obl = obliqueness(normals[pidx], positions[pidx], frames)
    return ViewArrays(pidx, v, np.asarray(nearest, dtype=np.int64), W, fov_all, roll, obl, in_sight)


def fly_clip(
    route: np.ndarray, point: np.ndarray, lim: Limits, q: MeshQueries, roll_pair: np.ndarray, p: int
) -> Clip:
    """Smooth, sample, verify and cut one clip along a route of cameras (module docstring, steps 3-5)."""
    # at most the budget of path: bounds the smoothing samples whatever the spacing
    route = trim(route, BUDGET_MARGIN * lim.spacing * (lim.max_frames - 1))
    route = route[np.concatenate([[True], np.linalg.norm(np.diff(route, axis=0), axis=1) > 1e-9])]
    if len(route) == 1:
        return verify_clip(route[:1], route, point, lim, q, roll_pair, p, lone=lim.max_frames > 1)
    frames = frames_along(smooth_path(route, lim.spacing, lim.turn_rate), lim.spacing)
    return verify_clip(frames, route, point, lim, q, roll_pair, p)


def push_out(frames: np.ndarray, q: MeshQueries, lim: Limits) -> np.ndarray:
    """Frames moved away from the mesh where they come closer than the clearance: along the direction
    from the nearest surface point (the distance gradient), by a Gaussian bump about one smallest radius
    of curvature wide so the path stays smooth, then resampled every spacing (module docstring, 4)."""
    if lim.clearance <= 0 or len(frames) < 3:
        return frames
    sigma = max(1.0, 1.0 / lim.turn_rate / lim.spacing)  # frames
    plateau = 2 * int(np.ceil(2 * sigma)) + 1  # the bump's full height spans +-2 sigma about each push ...
    full = float(erf(np.sqrt(2.0)))  # ... of which the Gaussian keeps this share at the pushed frame
    for _ in range(PUSH_ROUNDS):
        dist, closest = q.closest_within(frames, lim.clearance)
        near = np.flatnonzero((dist < lim.clearance) & (dist > 1e-9))
        if not len(near):
            break
        need = np.zeros(len(frames))
        need[near] = PUSH_MARGIN * lim.clearance - dist[near]
        away = np.zeros_like(frames)
        away[near] = (frames[near] - closest[near]) / dist[near, None] * need[near, None]
        # height: the largest push nearby, smoothed; direction: the pushes nearby, averaged
        height = (
            gaussian_filter1d(maximum_filter1d(need, plateau, mode="constant"), sigma, mode="constant") / full
        )
        direction = gaussian_filter1d(away, 2 * sigma, axis=0, mode="constant")
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        shift = np.where(norm > 0, direction / np.maximum(norm, 1e-300), 0.0) * height[:, None]
        # resampled along the arc of a fine spline: a push along the path must not bunch the frames
        frames = resample(
            frames_along(frames + shift, lim.spacing / DENSE_PER_PUSH), lim.spacing, keep_end=False
        )
    return frames


def verify_clip(
    frames: np.ndarray, anchors: np.ndarray, point: np.ndarray, lim: Limits, q: MeshQueries,
    roll_pair: np.ndarray, p: int,
    *,
    lone: bool = False,
) -> Clip:
    """Push out, verify and cut the frames of one clip (module docstring, steps 4-5); anchors: points in
    the free space the clip was planned through (its route's cameras, the axis of a loop), each frame in
    sight of its nearest."""
    frames = push_out(frames, q, lim)
    n = len(frames)
    fail: dict[str, np.ndarray] = {}
    fail["clearance"] = q.near_mesh(frames, lim.clearance) if lim.clearance > 0 else np.zeros(n, dtype=bool)
    nearest_anchor = anchors[cKDTree(anchors).query(frames)[1]]
    link_clear = q.line_of_sight(frames[:-1], frames[1:], 0.0) if n > 1 else np.ones(0, dtype=bool)
    fail["outside"] = ~q.line_of_sight(frames, nearest_anchor, 0.0)
    fail["hidden"] = (
        np.zeros(n, dtype=bool) if lim.ahead else ~q.line_of_sight(frames, np.tile(point, (n, 1)), lim.tol)
    )
    fail["hidden"] |= np.linalg.norm(frames - point, axis=1) < 1e-6  # never look at the point from itself
    turn = np.zeros(n, dtype=bool)
    if n > 2:
        turn[1:-1] = turn_angles(frames) > lim.turn_rate * lim.spacing * LIMIT_SLACK
    fail["turn"] = turn
    look = _look_targets(frames, point, lim.ahead)
    view_ok = np.ones(max(n - 1, 0), dtype=bool)
    if n > 1:
        W0 = look_at_batch(frames, look, np.zeros(n))
        view_ok = rotation_angles(W0) <= (1.0 - ROLL_SHARE) * lim.view_rate * lim.spacing * LIMIT_SLACK
    fail["view"] = np.zeros(n, dtype=bool)
    fail["view"][1:] |= ~view_ok
    good = ~(fail["clearance"] | fail["outside"] | fail["hidden"] | fail["turn"])
    a, b = longest_run(good, link_clear & view_ok)
    # a surface between two frames cuts the clip too (a link, not a frame): reported as the later frame
    # outside
    fail["outside"][1:] |= ~link_clear
    planned = min(n, lim.max_frames)
    if b - a > lim.max_frames:  # shorten the path, keep its middle
        a += (b - a - lim.max_frames) // 2
        b = a + lim.max_frames
    note = None
    cut = b - a < planned
    short = b - a < lim.min_frames
    if cut or lone or short:
        reasons = {k: int(v.sum()) for k, v in fail.items() if v.any()} if cut else {}
        if lone:
            reasons["route"] = 1
        elif short and not cut:
            reasons["short"] = 1
        if short:
            a = b
        note = ClipNote(point=p, frames=b - a, planned=planned, reasons=reasons)
    frames = frames[a:b]
    look = _look_targets(frames, point, lim.ahead)  # the tangent at a cut end is one-sided
    return Clip(frames, look, _roll(roll_pair, len(frames), lim), note)


def _look_targets(frames: np.ndarray, point: np.ndarray, ahead: bool) -> np.ndarray:
    """Where each frame looks: the point, or one metre along the path's tangent (central differences)."""
    if not ahead or len(frames) < 2:
        return np.tile(point, (len(frames), 1))
    t = np.gradient(frames, axis=0)
    return frames + t / np.linalg.norm(t, axis=1, keepdims=True)


def _roll(pair: np.ndarray, n: int, lim: Limits) -> np.ndarray:
    """Roll from pair[0] towards pair[1] along a smoothstep over the clip, at most ROLL_SHARE x view_rate
    radians per metre (smoothstep's steepest slope is 1.5 / length)."""
    if n < 2:
        return pair[:n].copy()
    length = lim.spacing * (n - 1)
    limit = ROLL_SHARE * lim.view_rate * length / 1.5
    span = float(np.clip(pair[1] - pair[0], -limit, limit))
    s = np.linspace(0.0, 1.0, n)
    return pair[0] + span * s * s * (3.0 - 2.0 * s)
