"""What a plan's views look like as distributions: the facts a user steers a dataset by (pure numpy).

Per view: field of view, pitch, roll, camera height above the floor, distance to the fixated point and
obliqueness; per point: its number of views. Degrees and metres, world frame +Z up (as in the plan).

- pitch: the angle of the optical axis above the horizontal, positive looking up (-90 straight down).
- roll: the turn of the image about the optical axis relative to gravity, as `camera.look_at` makes it
  (0: the image's up is as close to +Z as it can be; positive turns camera x towards world-down).
- height: camera z minus `floor_z`. Callers that hold the mesh pass the floor the camera generator uses
  (the lowest of `planning.cameras.detect_floors`); without it, the lowest point of the plan stands in
  (every point is seen by a camera, and in a room the lowest surface seen is the floor).
- obliqueness: the angle between the point's normal and the direction from the point to the camera.

The same formulas take any posed cameras (`camera_distributions`): a capture's or another dataset's cameras
are compared with a plan's on equal terms. Histograms use fixed edges per distribution (values beyond the
edges count in the end bins), so two specs' histograms overlay bin for bin.
"""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from services.core.domain.plan import SpacePlan

DISTRIBUTIONS = (
    "fov_deg", "pitch_deg", "roll_deg", "height_m", "distance_m", "obliqueness_deg", "views_per_point",
)
PER_POINT = ("views_per_point",)  # the others are per view
QUANTILES = {"q05": 0.05, "q25": 0.25, "q50": 0.5, "q75": 0.75, "q95": 0.95}

DEFAULT_BINS: dict[str, np.ndarray] = {
    "fov_deg": np.linspace(0.0, 180.0, 73),
    "pitch_deg": np.linspace(-90.0, 90.0, 73),
    "roll_deg": np.linspace(-45.0, 45.0, 37),
    "height_m": np.linspace(0.0, 3.0, 31),
    "distance_m": np.linspace(0.0, 10.0, 41),
    "obliqueness_deg": np.linspace(0.0, 90.0, 37),
    "views_per_point": np.arange(0.0, 41.0) + 0.5,  # one bin per count 1..40
}


class Histogram(TypedDict):
    edges: list[float]
    counts: list[int]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def pitch_roll_deg(world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll in degrees (module docstring) of (n, 4, 4) world_to_camera matrices, OpenCV axes."""
    R = np.asarray(world_to_camera, dtype=np.float64).reshape(-1, 4, 4)[:, :3, :3]
    x, z = R[:, 0], R[:, 2]  # camera right and forward axes in world coordinates
    pitch = np.degrees(np.arcsin(np.clip(z[:, 2], -1.0, 1.0)))
    # the roll-free right axis of look_at: forward x up (straight up/down views: forward x world +Y)
    x0 = np.cross(z, [0.0, 0.0, 1.0])
    flat = np.linalg.norm(x0, axis=1) < 1e-9
    x0[flat] = np.cross(z[flat], [0.0, 1.0, 0.0])
    x0 = _unit(x0)
    y0 = np.cross(z, x0)
    roll = np.degrees(np.arctan2(np.einsum("ij,ij->i", x, y0), np.einsum("ij,ij->i", x, x0)))
    return pitch, roll


def camera_centres(world_to_camera: np.ndarray) -> np.ndarray:
    """(n, 3) camera centres in world metres of (n, 4, 4) world_to_camera matrices."""
    W = np.asarray(world_to_camera, dtype=np.float64).reshape(-1, 4, 4)
    return -np.einsum("nji,nj->ni", W[:, :3, :3], W[:, :3, 3])


def camera_distributions(
    world_to_camera: np.ndarray, fov_rad: np.ndarray, floor_z: float
) -> dict[str, np.ndarray]:
    """fov, pitch, roll and height of any posed cameras: (n, 4, 4) world_to_camera, (n,) fov in radians."""
    pitch, roll = pitch_roll_deg(world_to_camera)
    return {
        "fov_deg": np.degrees(np.asarray(fov_rad, dtype=np.float64).reshape(-1)),
        "pitch_deg": pitch, "roll_deg": roll,
        "height_m": camera_centres(world_to_camera)[:, 2] - float(floor_z),
    }


def plan_floor_z(plan: SpacePlan) -> float:
    """The floor height a plan implies without its mesh: its lowest point (0 when it has none)."""
    if not plan.points:
        return 0.0
    return float(min(p.position[2] for p in plan.points))


def view_distributions(plan: SpacePlan, *, floor_z: float | None = None) -> dict[str, np.ndarray]:
    """Every distribution of DISTRIBUTIONS for a plan: per view, in plan.views order, and views_per_point per
    point in plan.points order (floor_z: see the module docstring)."""
    floor = plan_floor_z(plan) if floor_z is None else float(floor_z)
    n = len(plan.views)
    W = np.array([v.world_to_camera for v in plan.views]).reshape(n, 4, 4)
    fov = np.array([v.fov for v in plan.views], dtype=np.float64)
    values = camera_distributions(W, fov, floor)
    by_idx = {p.idx: p for p in plan.points}
    targets = np.array([by_idx[v.point_idx].position for v in plan.views]).reshape(n, 3)
    values["distance_m"] = np.linalg.norm(targets - camera_centres(W), axis=1)
    values["obliqueness_deg"] = np.degrees(np.array([v.obliqueness for v in plan.views], dtype=np.float64))
    counts: dict[int, int] = {}
    for v in plan.views:
        counts[v.point_idx] = counts.get(v.point_idx, 0) + 1
    values["views_per_point"] = np.array([counts.get(p.idx, 0) for p in plan.points], dtype=np.float64)
    return {k: values[k] for k in DISTRIBUTIONS}


def summary(values: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Quantiles q05..q95, mean and n of each distribution (an empty one has n = 0 and nothing else)."""
    out: dict[str, dict[str, float]] = {}
    for name, v in values.items():
        arr = np.asarray(v, dtype=np.float64).reshape(-1)
        arr = arr[np.isfinite(arr)]
        if not len(arr):
            out[name] = {"n": 0.0}
            continue
        q = np.quantile(arr, list(QUANTILES.values()))
        out[name] = {k: float(x) for k, x in zip(QUANTILES, q, strict=True)}
        out[name].update(mean=float(arr.mean()), n=float(len(arr)))
    return out


def histogram(values: np.ndarray, edges: np.ndarray) -> Histogram:
    """Counts of finite values in the bins of `edges`; values beyond the edges count in the end bins."""
    edges = np.asarray(edges, dtype=np.float64)
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    arr = np.clip(arr[np.isfinite(arr)], edges[0], edges[-1])
    counts, _ = np.histogram(arr, bins=edges)
    return {"edges": edges.tolist(), "counts": counts.astype(int).tolist()}


def histograms(
    values: dict[str, np.ndarray], *, bins: dict[str, np.ndarray] | None = None
) -> dict[str, Histogram]:
    """A histogram per distribution on fixed edges (DEFAULT_BINS unless `bins` names others)."""
    edges = {**DEFAULT_BINS, **(bins or {})}
    out = {}
    for name, v in values.items():
        if name not in edges:
            raise KeyError(f"no bin edges for {name!r}: pass them in bins (known: {sorted(edges)})")
        out[name] = histogram(v, edges[name])
    return out


def ks_statistic(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov statistic: the largest gap between the two empirical CDFs (1 when either
    sample is empty)."""
    a = np.sort(np.asarray(a, dtype=np.float64).reshape(-1))
    b = np.sort(np.asarray(b, dtype=np.float64).reshape(-1))
    if not len(a) or not len(b):
        return 1.0
    x = np.concatenate([a, b])
    cdf_a = np.searchsorted(a, x, side="right") / len(a)
    cdf_b = np.searchsorted(b, x, side="right") / len(b)
    return float(np.abs(cdf_a - cdf_b).max())


def histogram_quantile(hist: Histogram, level: float) -> float:
    """The quantile at `level` of the values a histogram counts, linear within its bin."""
    counts = np.asarray(hist["counts"], dtype=np.float64)
    edges = np.asarray(hist["edges"], dtype=np.float64)
    cdf = np.concatenate([[0.0], np.cumsum(counts)]) / max(counts.sum(), 1.0)
    i = int(np.clip(np.searchsorted(cdf, level, side="left"), 1, len(edges) - 1))
    lo, hi = cdf[i - 1], cdf[i]
    t = 0.0 if hi <= lo else (level - lo) / (hi - lo)
    return float(edges[i - 1] + t * (edges[i] - edges[i - 1]))


class PlanDistributions:
    """A plan's distributions gathered chunk by chunk in bounded memory (the scheduler plans in chunks):
    counts on DEFAULT_BINS, and sums for the means. Quantiles are read off the histograms (within a bin)."""

    def __init__(self, floor_z: float | None):
        self.floor_z = floor_z
        self.counts = {name: np.zeros(len(DEFAULT_BINS[name]) - 1, dtype=np.int64) for name in DISTRIBUTIONS}
        self.sums = dict.fromkeys(DISTRIBUTIONS, 0.0)
        self.n = dict.fromkeys(DISTRIBUTIONS, 0)

    def add(self, plan: SpacePlan) -> None:
        """Count the views (and points) of a plan or of one chunk of it."""
        floor = self.floor_z if self.floor_z is not None else plan_floor_z(plan)
        values = view_distributions(plan, floor_z=floor)
        for name, v in values.items():
            v = v[np.isfinite(v)]
            self.counts[name] += np.asarray(histogram(v, DEFAULT_BINS[name])["counts"], dtype=np.int64)
            self.sums[name] += float(v.sum())
            self.n[name] += len(v)

    def record(self) -> dict[str, object]:
        """JSON-ready: floor_z, a summary per distribution (as `summary`, quantiles from the histograms)
        and the histograms themselves."""
        hists: dict[str, Histogram] = {
            name: {"edges": DEFAULT_BINS[name].tolist(), "counts": self.counts[name].tolist()}
            for name in DISTRIBUTIONS
        }
        out: dict[str, dict[str, float]] = {}
        for name in DISTRIBUTIONS:
            n = self.n[name]
            out[name] = {"n": float(n)}
            if n:
                out[name] = {k: histogram_quantile(hists[name], q) for k, q in QUANTILES.items()}
                out[name].update(mean=self.sums[name] / n, n=float(n))
        return {"floor_z": self.floor_z, "summary": out, "histograms": hists}
