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

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import sparse
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from scipy.special import erf

from services.core.domain.jobspec import ViewSpec
from services.scheduler.planning.views import (
    ViewArrays,
    cap_views,
    look_at_batch,
    obliqueness,
    truncated_normal,
)
from services.scheduler.planning.visibility import MeshQueries

EDGE_REACH = 2.5  # edge length limit in median nearest-camera distances
EDGE_KNN = 6  # and each camera's nearest neighbours, so sparse cameras stay connected
MAX_WAYPOINTS = 16
# lengths in camera spacings (the median nearest-camera distance: about 0.5 m in rooms), so the same
# rules fit a room and cameras around an object
LEG = 6.0  # a leg ends at a camera at most this far (straight line) from where it starts
WAYPOINT_SEP = 2.0  # from earlier waypoints
GOOD_LEG = 3.0  # legs longer than this (along the path) score no better
LEAD = 2.0  # a leg's heading: towards its first camera this far from its start
MIN_WAYPOINT_DEGREE = 3
MAX_LEG_TURN_COS = 0.0  # a new leg heads within 90 degrees of the last one: no reversals
MAX_NODE_TURN = float(np.radians(100.0))  # sharpest turn at a camera on the route
BUDGET_MARGIN = 1.25  # route this much longer than the clip: verification may cut some of it
DENSE_PER_FRAME = 2  # smoothing samples per frame spacing ...
MAX_SAMPLES_PER_RADIUS = 40  # ... or per smallest radius of curvature when frames are closer
SIGMA_GROWTH = 1.5
SMOOTHING_LEVELS = 9
FAIRING_MARGIN = 0.8  # smooth to this share of the limit: frames span several dense samples
ROLL_SHARE = 0.1  # of the view-rate limit that roll may use
ROUTE_VIEW_SHARE = 0.75  # of the view-rate limit that route edges may need: smoothing moves the path
LIMIT_SLACK = 1.0 + 1e-6
PUSH_MARGIN = 1.05  # frames too near the mesh are pushed to this x the clearance ...
PUSH_ROUNDS = 3  # ... at most this many times (a push can bring a neighbour near)
DENSE_PER_PUSH = 8  # spline samples per frame spacing when a pushed path is resampled
LOOP_CANDIDATES = 8  # loop centres tried per point (rooms) ...
LOOP_PROBES = 16  # ... of those whose free radius, probed by this many level rays, is largest
LOOP_SHARE = 0.9  # of the limits a loop may use (its frames are exact: no smoothing moves them)
LOOP_RADIUS_GROWTH = 1.25  # loop radius: this x the smallest the turn limit allows, where the room allows
LOOP_HEIGHT_SWING = 0.15  # metres up and down: each lap at another height ...
LOOP_SWING_RATE = 0.37  # ... swinging this many cycles per radian of lap (no whole fraction: laps differ)
ARC_RADII = (1.05, 1.4, 1.8)  # circles round a point: radii in the least the limits allow
OBJECT_REFERENCE_M = 5.0  # object clips are planned as if their camera sphere had this radius (step 6)
ORBIT_TILT_DEG = (42.0, 8.0)  # object orbits: angle between the axis and the camera, mean and swing


@dataclass
class ClipNote:
    """Why a point's clip is shorter than planned (or missing): sampled point index, frames kept and
    planned, and how many frames failed each check (keys of services.core.domain.plan.CLIP_CHECKS)."""

    point: int
    frames: int
    planned: int
    reasons: dict[str, int] = field(default_factory=dict)

    def as_dict(self, point_idx: int | None) -> dict[str, Any]:
        """The JSON form, naming the point by its index in the plan (None: not in the plan)."""
        return {
            "point_idx": point_idx, "outcome": "dropped" if self.frames == 0 or point_idx is None else "shortened",
            "frames": self.frames, "planned_frames": self.planned, "reasons": dict(sorted(self.reasons.items())),
        }


def attainable_clearance(cameras: np.ndarray, q: MeshQueries, clearance: float) -> float:
    """The clearance (m) frames are held to: `clearance`, or for provided or object cameras closer to
    the mesh than that, the largest clearance / 2^k (k <= 10) that every camera keeps (generated
    cameras always keep cameras.clearance_m)."""
    for _ in range(11):
        if clearance <= 0 or not q.near_mesh(cameras, clearance).any():
            return clearance
        clearance /= 2
    return 0.0


def camera_spacing(cameras: np.ndarray) -> float:
    """Median distance (m) from a camera to its nearest other camera (1 for fewer than two)."""
    if len(cameras) < 2:
        return 1.0
    d, _ = cKDTree(cameras).query(cameras, k=2)
    return float(np.median(d[:, 1]))


def free_space_graph(cameras: np.ndarray, q: MeshQueries, clearance: float) -> sparse.csr_matrix:
    """(n, n) symmetric sparse graph of collision-free edges between cameras, weights in metres."""
    n = len(cameras)
    if n < 2:
        return sparse.csr_matrix((n, n))
    tree = cKDTree(cameras)
    k = min(EDGE_KNN + 1, n)
    _, nn = tree.query(cameras, k=k)
    reach = EDGE_REACH * camera_spacing(cameras)
    near = tree.query_pairs(reach, output_type="ndarray").reshape(-1, 2)
    knn = np.stack([np.repeat(np.arange(n), k - 1), nn[:, 1:].ravel()], axis=1)
    pairs = np.unique(np.sort(np.concatenate([near, knn]), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    a, b = cameras[pairs[:, 0]], cameras[pairs[:, 1]]
    ok = q.line_of_sight(a, b, 0.0)
    length = np.linalg.norm(b - a, axis=1)
    if clearance > 0 and ok.any():
        live = np.flatnonzero(ok)
        steps = np.maximum(np.ceil(length[live] / (clearance / 2)).astype(np.int64), 1)
        inner = steps - 1  # samples strictly between the cameras, k / steps of the way for k = 1..inner
        edge = np.repeat(live, inner)
        k = np.arange(len(edge)) - np.repeat(np.cumsum(inner) - inner, inner) + 1
        samples = a[edge] + (k / np.repeat(steps, inner))[:, None] * (b[edge] - a[edge])
        ok[np.unique(edge[q.near_mesh(samples, clearance)])] = False
    return _symmetric(pairs[ok, 0], pairs[ok, 1], length[ok], n)


def _symmetric(i: np.ndarray, j: np.ndarray, w: np.ndarray, n: int) -> sparse.csr_matrix:
    """(n, n) undirected graph with edges (i, j) of weight w."""
    return sparse.csr_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))


def point_graph(
    graph: sparse.csr_matrix, xyz: np.ndarray, point: np.ndarray, view_rate: float, q: MeshQueries, tol: float
) -> sparse.csr_matrix:
    """The free-space graph of the cameras that see a point, keeping the edges a fixated clip can fly:
    the middle sees the point, and moving along the edge turns the camera fixated on the point by at
    most view_rate radians per metre (at the ends and the middle): moving sideways close to the point
    turns it fast, moving towards it does not."""
    coo = sparse.triu(graph).tocoo()
    a, b = xyz[coo.row], xyz[coo.col]
    t = _unit(b - a)
    rate = np.zeros(len(a))
    eps = 1e-3  # metres: the rotation of the fixated camera over a small step, as the frames measure it
    targets = np.tile(point, (len(a), 1))
    for x in (a, (a + b) / 2, b):
        pair = np.stack([look_at_batch(x, targets, np.zeros(len(x))),
                         look_at_batch(x + eps * t, targets, np.zeros(len(x)))], axis=1)
        angle = np.arccos(np.clip((np.einsum("nij,nij->n", pair[:, 0, :3, :3], pair[:, 1, :3, :3]) - 1) / 2, -1, 1))
        rate = np.maximum(rate, angle / eps)
    keep = rate <= view_rate
    keep[keep] = q.line_of_sight((a[keep] + b[keep]) / 2, np.tile(point, (int(keep.sum()), 1)), tol)
    return _symmetric(coo.row[keep], coo.col[keep], coo.data[keep], graph.shape[0])


def choose_route(
    graph: sparse.csr_matrix, xyz: np.ndarray, point: np.ndarray, budget: float, view_radius: float,
    unit: float, rng: np.random.Generator,
) -> np.ndarray:
    """Node indices (into xyz) of a route through a handful of waypoints (module docstring, step 2);
    unit: the camera spacing, metres."""
    far = np.linalg.norm(xyz - point, axis=1) >= view_radius
    # waypoints where the route can go on: not dead ends (corners, under furniture)
    degree = np.diff(graph.indptr)
    open_ = degree >= MIN_WAYPOINT_DEGREE if (degree >= MIN_WAYPOINT_DEGREE).any() else degree >= 0
    start = far & open_
    pool = np.flatnonzero(start) if start.any() else np.array([int(np.argmax(np.where(open_, np.linalg.norm(xyz - point, axis=1), -1)))])
    route = [int(rng.choice(pool))]
    waypoints = list(route)
    length = 0.0
    # grow forwards, then backwards from the start (the reversed route grows at its end)
    length = _grow(graph, xyz, route, waypoints, far, open_, length, budget, unit)
    route.reverse()
    _grow(graph, xyz, route, waypoints, far, open_, length, budget, unit)
    return np.array(route, dtype=np.int64)


def _grow(
    graph: sparse.csr_matrix, xyz: np.ndarray, route: list[int], waypoints: list[int], far: np.ndarray,
    open_: np.ndarray, length: float, budget: float, unit: float,
) -> float:
    """Append legs to `route` (and their ends to `waypoints`) while the budget lasts; the new length."""
    for _ in range(MAX_WAYPOINTS - len(waypoints)):
        if length >= budget:
            break
        cost, pred = csgraph.dijkstra(graph, indices=route[-1], return_predecessors=True)
        here = xyz[route[-1]]
        clear = np.linalg.norm(xyz[:, None] - xyz[waypoints][None], axis=2).min(axis=1) >= WAYPOINT_SEP * unit
        cand = np.flatnonzero(np.isfinite(cost) & clear & open_ & (np.linalg.norm(xyz - here, axis=1) <= LEG * unit))
        if not len(cand):
            break
        legs = [xyz[_path(pred, route[-1], int(c))] for c in cand]
        leg_length = cost[cand]  # edge weights are lengths, metres
        bend = np.ones(len(cand))
        if len(route) > 1:
            heading = _unit(here - xyz[route[-2]])
            bend = np.array([_unit(_lead(leg, LEAD * unit) - here) @ heading for leg in legs])
        # no node of the leg (nor its joint with the route) doubles back: a cusp cannot be smoothed
        joint = [np.vstack([xyz[route[-2:-1]], leg]) for leg in legs]
        sharpest = np.array([turn_angles(j).max() if len(j) > 2 else 0.0 for j in joint])
        bend[sharpest > MAX_NODE_TURN] = -1.0
        # legs that go straight on, away from the point (fixating a near point turns the view fast), long
        # but not so long that they end at a wall with nowhere to go on
        score = (np.minimum(leg_length, min(GOOD_LEG * unit, budget - length)) * np.where(far[cand], 1.0, 0.5)
                 * (1.0 + bend) - 1e-9 * leg_length)
        score[bend <= MAX_LEG_TURN_COS] = -np.inf
        best = int(np.argmax(score))
        if not np.isfinite(score[best]):
            break
        nxt = int(cand[best])
        length += float(leg_length[best])
        route.extend(_path(pred, route[-1], nxt)[1:])
        waypoints.append(nxt)
    return length


def _lead(leg: np.ndarray, reach: float) -> np.ndarray:
    """The first point of a leg at least `reach` metres from its start (its end when none is): its heading."""
    far = np.flatnonzero(np.linalg.norm(leg - leg[0], axis=1) >= reach)
    return leg[far[0]] if len(far) else leg[-1]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _path(pred: np.ndarray, src: int, dst: int) -> list[int]:
    out = [dst]
    while out[-1] != src:
        out.append(int(pred[out[-1]]))
    return out[::-1]


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


@dataclass
class Clip:
    """One point's clip: frame positions (world metres), look-at targets, roll (radians), and the note
    when it was cut short or dropped."""

    frames: np.ndarray  # (n, 3)
    look: np.ndarray  # (n, 3) targets
    roll: np.ndarray
    note: ClipNote | None


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
        return cls(spec.trajectory_spacing_m * scale, float(turn_rate), float(view_rate), spec.trajectory_max_frames,
                   spec.trajectory_min_frames, ahead, clearance, tol)


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
    rmax = np.radians(spec.roll_max_deg)
    fov_args = (np.radians(spec.fov_mean_deg), np.radians(spec.fov_std_deg),
                np.radians(spec.fov_min_deg), np.radians(spec.fov_max_deg))
    clearance = attainable_clearance(cameras, q, clearance)
    lim = Limits.of(spec, clearance, tol, orbit[1] / OBJECT_REFERENCE_M if orbit is not None else 1.0)
    budget = BUDGET_MARGIN * lim.spacing * (lim.max_frames - 1)
    graph = free_space_graph(cameras, q, clearance) if orbit is None else sparse.csr_matrix((len(cameras),) * 2)
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
        roll_pair = rng.uniform(-rmax, rmax, 2)
        fov = float(truncated_normal(rng, *fov_args, 1)[0])
        clips: list[Clip] = []
        if orbit is not None:
            loops = object_orbits(positions[p], normals[p], cameras[cams], orbit[1], lim, rng)
        else:
            sub = graph[cams][:, cams]
            if not lim.ahead:
                sub = point_graph(sub, cameras[cams], positions[p], ROUTE_VIEW_SHARE * lim.view_rate, q, tol)
            node = choose_route(sub, cameras[cams], positions[p], budget, 1.0 / lim.view_rate, unit, rng)
            clips.append(fly_clip(cameras[cams][node], positions[p], lim, q, roll_pair, p))
            loops = room_loops(positions[p], cameras[cams], lim, q, rng) + point_arcs(positions[p], cameras[cams], lim, rng)
        clips += [verify_clip(frames, anchors, positions[p], lim, q, roll_pair, p) for frames, anchors in loops]
        clip = max(clips, key=lambda c: len(c.frames))  # the first of the longest
        if clip.note is not None:
            notes.append(clip.note)
        n = len(clip.frames)
        P.append(np.full(n, p, dtype=np.int64))
        F.append(clip.frames)
        T.append(clip.look)
        R.append(clip.roll)
        FOV.append(np.full(n, fov))
    pidx = np.concatenate(P) if P else np.zeros(0, dtype=np.int64)
    if not len(pidx):
        z = np.zeros(0)
        return ViewArrays(z.astype(np.int64), z.astype(np.int64), z.astype(np.int64), np.zeros((0, 4, 4)),
                          z, z, z, z.astype(bool)), notes
    frames = np.concatenate(F)
    roll = np.concatenate(R)
    fov_all = np.concatenate(FOV)
    counts = np.bincount(pidx, minlength=len(visible))
    v = np.arange(len(pidx)) - np.repeat(np.cumsum(counts) - counts, counts)
    W = look_at_batch(frames, np.concatenate(T), roll)
    _, nearest = tree.query(frames)
    in_sight = q.line_of_sight(frames, positions[pidx], tol)
    obl = obliqueness(normals[pidx], positions[pidx], frames)
    return ViewArrays(pidx, v, np.asarray(nearest, dtype=np.int64), W, fov_all, roll, obl, in_sight), notes


def fly_clip(route: np.ndarray, point: np.ndarray, lim: Limits, q: MeshQueries, roll_pair: np.ndarray, p: int) -> Clip:
    """Smooth, sample, verify and cut one clip along a route of cameras (module docstring, steps 3-5)."""
    # at most the budget of path: bounds the smoothing samples whatever the spacing
    route = trim(route, BUDGET_MARGIN * lim.spacing * (lim.max_frames - 1))
    route = route[np.concatenate([[True], np.linalg.norm(np.diff(route, axis=0), axis=1) > 1e-9])]
    if len(route) == 1:
        return verify_clip(route[:1], route, point, lim, q, roll_pair, p, lone=lim.max_frames > 1)
    frames = frames_along(smooth_path(route, lim.spacing, lim.turn_rate), lim.spacing)
    return verify_clip(frames, route, point, lim, q, roll_pair, p)


def spiral(
    base: np.ndarray, axis: np.ndarray, radius: Callable[[np.ndarray], np.ndarray],
    along: Callable[[np.ndarray], np.ndarray], lim: Limits, rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Frames every lim.spacing (at most lim.max_frames) of a loop around the line through `base` along
    `axis`: at lap angle phi (from a random start, either way round) the camera is radius(phi) from the
    line and along(phi) along it; and the points of the line the loop winds round (its anchors)."""
    axis = _unit(axis)
    u = _unit(np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0]))
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
    loops = [(ok[i], r) for i in best if radius[i] >= tight for r in sorted({float(radius[i]), tight}, reverse=True)]
    up = np.array([0.0, 0.0, 1.0])
    return [spiral(cams[c], up, _constant(r), _height_swing, lim, rng) for c, r in loops]


def point_arcs(point: np.ndarray, cams: np.ndarray, lim: Limits, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Level circles round the point itself at the cameras' median height (module docstring, step 2b):
    where the room allows no loop in front of a point, the arc of such a circle that stays in the room
    and in sight is often longer than a route; the cameras that see the point are its anchors."""
    if not len(cams):
        return []
    base = np.array([point[0], point[1], float(np.median(cams[:, 2]))])
    nearest = max(1.0 / (LOOP_SHARE * (1.0 - ROLL_SHARE) * lim.view_rate), 1.0 / (LOOP_SHARE * lim.turn_rate))
    out = []
    for growth in ARC_RADII:
        frames, _ = spiral(base, np.array([0.0, 0.0, 1.0]), _constant(growth * nearest), _height_swing, lim, rng)
        out.append((frames, cams))
    return out


def _constant(value: float) -> Callable[[np.ndarray], np.ndarray]:
    def at(phi: np.ndarray) -> np.ndarray:
        return np.full(len(phi), value)
    return at


def _height_swing(phi: np.ndarray) -> np.ndarray:
    return LOOP_HEIGHT_SWING * np.sin(LOOP_SWING_RATE * phi)


def object_orbits(
    point: np.ndarray, normal: np.ndarray, cams: np.ndarray, distance: float, lim: Limits, rng: np.random.Generator,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Orbits `distance` from the point round an axis through it (its normal; the mean direction to the
    cameras that see it; up), tilted ORBIT_TILT_DEG from the axis with a slow swing (module docstring, 2b)."""
    mean_tilt, swing = np.radians(ORBIT_TILT_DEG)
    # and up: a steep axis would carry the camera over the point, where looking down spins the view
    axes = [normal] + ([_unit(_unit(cams - point).mean(axis=0))] if len(cams) else []) + [np.array([0.0, 0.0, 1.0])]

    def tilt(phi: np.ndarray) -> np.ndarray:
        return mean_tilt + swing * np.sin(LOOP_SWING_RATE * phi)

    def off_axis(phi: np.ndarray) -> np.ndarray:
        return distance * np.sin(tilt(phi))

    def along_axis(phi: np.ndarray) -> np.ndarray:
        return distance * np.cos(tilt(phi))

    return [spiral(point, a, off_axis, along_axis, lim, rng) for a in axes]


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
        height = gaussian_filter1d(maximum_filter1d(need, plateau, mode="constant"), sigma, mode="constant") / full
        direction = gaussian_filter1d(away, 2 * sigma, axis=0, mode="constant")
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        shift = np.where(norm > 0, direction / np.maximum(norm, 1e-300), 0.0) * height[:, None]
        # resampled along the arc of a fine spline: a push along the path must not bunch the frames
        frames = resample(frames_along(frames + shift, lim.spacing / DENSE_PER_PUSH), lim.spacing, keep_end=False)
    return frames


def verify_clip(
    frames: np.ndarray, anchors: np.ndarray, point: np.ndarray, lim: Limits, q: MeshQueries, roll_pair: np.ndarray,
    p: int, *, lone: bool = False,
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
    fail["hidden"] = np.zeros(n, dtype=bool) if lim.ahead else ~q.line_of_sight(frames, np.tile(point, (n, 1)), lim.tol)
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
    # a surface between two frames cuts the clip too (a link, not a frame): reported as the later frame outside
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
