"""Fit a JobSpec to a target's camera distributions (a capture's, or another dataset's): steering by example.

The method, in the target's own terms: each fitted distribution is given to the spec as its quantiles at
`levels` equally spaced levels (services.core.domain.steering_spec), so the spec samples the target's shape:
  fov_deg   -> views.fov_quantiles_deg (drawn exactly),
  pitch_deg -> views.pitch_quantiles_deg (camera-point pairs thinned by pitch),
  height_m  -> cameras.height_quantiles_m, with cameras.floors 'lowest' (heights are measured above the lowest
               floor, as steering.view_distributions takes them),
  roll_deg  -> views.roll_quantiles_deg (drawn exactly),
  and cameras.enclosed false when most target cameras are not enclosed by the mesh (a partial scan).
A plan's views do not follow the camera heights and pair pitches exactly (Poisson-disc spacing, clearance,
which cameras see the points, points dropped below min_views), so the spec is re-planned and each quantile
is moved by half the gap between the target's quantile and the plan's at the same level, a few rounds; the
round with the smallest largest two-sample KS statistic is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.core.domain.jobspec import JobSpec
from services.core.domain.steering import ks_statistic, view_distributions
from services.core.domain.steering_spec import FOV_LIMITS_DEG, MAX_QUANTILES
from services.core.ingest.capture import find_capture
from services.core.ingest.guard.archive import MESH_SUFFIXES
from services.core.ingest.loading import LoadedSpace, load_space
from services.core.ingest.targets import Target, TargetError, capture_target, csv_target, point_info_target
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.cameras import detect_floors, inside_by_parity
from services.scheduler.planning.visibility import MeshQueries

# distribution -> (JobSpec section, knob, bounds of its values)
KNOBS = {
    "fov_deg": ("views", "fov_quantiles_deg", FOV_LIMITS_DEG),
    "pitch_deg": ("views", "pitch_quantiles_deg", (-90.0, 90.0)),
    "height_m": ("cameras", "height_quantiles_m", (0.0, 100.0)),
    "roll_deg": ("views", "roll_quantiles_deg", (-180.0, 180.0)),
}
FITTED = tuple(KNOBS)


@dataclass
class FitResult:
    """The fitted spec, its plan's KS statistic per distribution, and every round's."""

    spec: JobSpec
    ks: dict[str, float]
    rounds: list[dict[str, float]] = field(default_factory=list)
    values: dict[str, np.ndarray] = field(default_factory=dict)  # the fitted plan's distributions


def with_knobs(spec: JobSpec, cameras: dict[str, object], views: dict[str, object]) -> JobSpec:
    """`spec` with these camera and view knobs set (validated again)."""
    data = spec.model_dump(mode="json")
    data["cameras"].update(cameras)
    data["views"].update(views)
    return JobSpec.model_validate(data)


def _knob_update(quantiles: dict[str, np.ndarray], enclosed: bool
                 ) -> tuple[dict[str, object], dict[str, object]]:
    cameras: dict[str, object] = {}
    views: dict[str, object] = {}
    for name, q in quantiles.items():
        section, knob, _ = KNOBS[name]
        (cameras if section == "cameras" else views)[knob] = [float(x) for x in q]
    if "height_m" in quantiles:
        cameras["floors"] = "lowest"
    if not enclosed:
        cameras["enclosed"] = False
    return cameras, views


STEP = 0.5  # of the gap per round: a plan's quantiles are noisy, a full step chases the noise


def _corrected(q: np.ndarray, want: np.ndarray, got: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    """Quantiles moved by STEP times the gap between the target's and the plan's at each level, kept
    non-decreasing."""
    return np.maximum.accumulate(np.clip(q + STEP * (want - got), *bounds))


def fit_spec(space: LoadedSpace, spec: JobSpec, target: dict[str, np.ndarray], *, floor_z: float,
             enclosed: bool = True, space_name: str = "space", rounds: int = 6, levels: int = 21,
             tolerance: float = 0.05) -> FitResult:
    """Fit `spec`'s fov, pitch, height and roll to `target` (named as steering.DISTRIBUTIONS; any subset)
    on `space` (module docstring); stops early once every KS statistic is <= tolerance. `enclosed` false
    (see target_enclosed) lets cameras stand where the mesh does not enclose."""
    lv = np.linspace(0.0, 1.0, min(levels, MAX_QUANTILES))
    names = [n for n in FITTED if n in target and len(target[n])]
    if spec.views.mode == "trajectory":  # a clip's pitch follows its path: not a knob
        names = [n for n in names if n != "pitch_deg"]
    want = {n: np.quantile(np.asarray(target[n], dtype=np.float64), lv) for n in names}
    q = {n: np.clip(want[n], *KNOBS[n][2]) for n in names}
    best: FitResult | None = None
    history: list[dict[str, float]] = []
    for _ in range(max(1, rounds)):
        fitted = with_knobs(spec, *_knob_update(q, enclosed))
        plan = make_plan(space, fitted, space_rng(fitted.seed, space_name), space_name)
        values = view_distributions(plan, floor_z=floor_z)
        ks = {n: ks_statistic(values[n], target[n]) for n in names}
        history.append(ks)
        if best is None or max(ks.values(), default=0.0) < max(best.ks.values(), default=0.0):
            best = FitResult(fitted, ks, values=values)
        if max(ks.values(), default=0.0) <= tolerance or not len(values["pitch_deg"]):
            break
        q = {n: _corrected(q[n], want[n], np.quantile(values[n], lv), KNOBS[n][2]) for n in names}
    assert best is not None
    best.rounds = history
    return best


def target_enclosed(space: LoadedSpace, positions: np.ndarray) -> bool:
    """Whether most target camera centres (world metres) are enclosed by the mesh, as generated cameras must
    be by default (a partial scan's capture stands where the mesh does not enclose)."""
    if not len(positions):
        return True
    inside = inside_by_parity(MeshQueries(space.mesh), np.asarray(positions, dtype=np.float64))
    return bool(inside.mean() >= 0.5)


def floor_z(space: LoadedSpace) -> float | None:
    """The lowest floor of a world-frame scan (planning.cameras.detect_floors), None when it has none."""
    floors = detect_floors(space.mesh)
    return floors[0].z if floors else None


def _rotation_onto_z(up: np.ndarray) -> np.ndarray:
    """4x4 rotation taking the unit vector `up` onto +Z (Rodrigues; a half turn about x when up is -Z)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    T = np.eye(4)
    if c < -1 + 1e-12:
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        return T
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    T[:3, :3] = np.eye(3) + vx + vx @ vx / (1.0 + c)
    return T


def _has_mesh(path: Path) -> bool:
    if path.is_file():
        return path.suffix.lower() in MESH_SUFFIXES or path.suffix.lower() == ".zip"
    return any(p.suffix.lower() in MESH_SUFFIXES for p in path.iterdir() if p.is_file())


def load_target(path: Path, scan: tuple[Path, LoadedSpace] | None = None) -> Target:
    """The target at `path` (services.core.ingest.targets): a CSV, a folder of point_info JSONs, a scan with
    its capture (heights above that scan's lowest floor; `scan` is reused when it is the same path), or a
    capture alone (levelled by the cameras' mean up; no heights without a floor)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return csv_target(path)
    if path.is_dir() and next(path.rglob("*point_info*.json"), None) is not None:
        return point_info_target(path)
    if scan is not None and scan[0].resolve() == path.resolve():
        space = scan[1]
    elif _has_mesh(path):
        space = load_space(path)
    else:
        capture = find_capture(path)
        up = capture.mean_up() if capture is not None else None
        if capture is None or up is None:
            raise TargetError(f"{path}: no CSV, point_info, scan or posed capture found (or its cameras "
                              "agree on no up direction)")
        return capture_target(capture.in_world(_rotation_onto_z(up)), None)
    if space.capture is None:
        raise TargetError(f"{path}: the scan has no posed capture beside it")
    return capture_target(space.capture, floor_z(space))
