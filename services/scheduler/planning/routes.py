"""Routes for trajectory clips: the free-space graph of the cameras and a route of legs through it per point.

Steps 1 and 2 of services.scheduler.planning.trajectory (its docstring has the rules and why). Lengths are in
camera spacings (the median nearest-camera distance, about 0.5 m in rooms), so the same rules fit a room and
cameras around an object.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from services.scheduler.planning.paths import turn_angles, unit_vector
from services.scheduler.planning.views import look_at_batch
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
    return sparse.csr_matrix(
        (np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n)
    )


def point_graph(
    graph: sparse.csr_matrix, xyz: np.ndarray, point: np.ndarray, view_rate: float, q: MeshQueries, tol: float
) -> sparse.csr_matrix:
    """The free-space graph of the cameras that see a point, keeping the edges a fixated clip can fly:
    the middle sees the point, and moving along the edge turns the camera fixated on the point by at
    most view_rate radians per metre (at the ends and the middle): moving sideways close to the point
    turns it fast, moving towards it does not."""
    coo = sparse.triu(graph).tocoo()
    a, b = xyz[coo.row], xyz[coo.col]
    t = unit_vector(b - a)
    rate = np.zeros(len(a))
    eps = 1e-3  # metres: the rotation of the fixated camera over a small step, as the frames measure it
    targets = np.tile(point, (len(a), 1))
    for x in (a, (a + b) / 2, b):
        pair = np.stack([look_at_batch(x, targets, np.zeros(len(x))),
                         look_at_batch(x + eps * t, targets, np.zeros(len(x)))], axis=1)
        angle = np.arccos(
            np.clip((np.einsum("nij,nij->n", pair[:, 0, :3, :3], pair[:, 1, :3, :3]) - 1) / 2, -1, 1)
        )
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
    pool = (
        np.flatnonzero(start)
        if start.any()
        else np.array([int(np.argmax(np.where(open_, np.linalg.norm(xyz - point, axis=1), -1)))])
    )
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
        cand = np.flatnonzero(
            np.isfinite(cost) & clear & open_ & (np.linalg.norm(xyz - here, axis=1) <= LEG * unit)
        )
        if not len(cand):
            break
        legs = [xyz[_path(pred, route[-1], int(c))] for c in cand]
        leg_length = cost[cand]  # edge weights are lengths, metres
        bend = np.ones(len(cand))
        if len(route) > 1:
            heading = unit_vector(here - xyz[route[-2]])
            bend = np.array([unit_vector(_lead(leg, LEAD * unit) - here) @ heading for leg in legs])
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


def _path(pred: np.ndarray, src: int, dst: int) -> list[int]:
    out = [dst]
    while out[-1] != src:
        out.append(int(pred[out[-1]]))
    return out[::-1]
