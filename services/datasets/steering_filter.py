"""Keep a dataset's views whose steering values lie in given ranges, e.g. `where={"pitch_deg": (-10, 10)}`.

The values are those of services.core.domain.steering (per view; views_per_point of the view's point), taken
from each space's plan JSON (job.json's `plan` key) with the floor job.json records for it, so filtering reads
one file per space. Without a plan (the released Omnidata components), from each view's point_info, with the
recorded floor or else the lowest point_location of the space's views.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np

from services.core.domain.job_document import JobDocument
from services.core.domain.plan import plan_from_json
from services.core.domain.steering import DISTRIBUTIONS, PER_POINT, camera_distributions, view_distributions
from services.core.storage import ObjectNotFoundError, ObjectStore
from services.datasets.source import ViewRecord

Ranges = Mapping[str, tuple[float, float]]
ViewValues = dict[tuple[int, int], dict[str, float]]  # (point, view) -> name -> value


def check_ranges(where: Ranges) -> None:
    """ValueError naming an unknown distribution or a range that is not (lo, hi) with lo <= hi."""
    for name, bounds in where.items():
        if name not in DISTRIBUTIONS:
            raise ValueError(f"where: unknown distribution {name!r}; known: {', '.join(DISTRIBUTIONS)}")
        if len(bounds) != 2 or not float(bounds[0]) <= float(bounds[1]):
            raise ValueError(f"where[{name!r}] must be (lo, hi) with lo <= hi, got {bounds!r}")


def _space_record(job: JobDocument | None, space: str) -> Mapping[str, object]:
    spaces: Mapping[str, Mapping[str, object]] = job["spaces"] if job and job.get("spaces") else {}
    return spaces.get(space) or {}


def _floor(record: Mapping[str, object]) -> float | None:
    dist = record.get("distributions")
    floor = dist.get("floor_z") if isinstance(dist, dict) else None
    return float(floor) if isinstance(floor, int | float) else None


def _from_plan(store: ObjectStore, key: str, floor: float | None) -> ViewValues | None:
    try:
        plan = plan_from_json(store.get_bytes(key))
    except ObjectNotFoundError:
        return None
    values = view_distributions(plan, floor_z=floor)
    per_point = {p.idx: values["views_per_point"][i] for i, p in enumerate(plan.points)}
    out: ViewValues = {}
    for i, view in enumerate(plan.views):
        row = {n: float(values[n][i]) for n in DISTRIBUTIONS if n not in PER_POINT}
        out[(view.point_idx, view.v)] = {**row, "views_per_point": float(per_point[view.point_idx])}
    return out


def _from_point_info(store: ObjectStore, records: list[ViewRecord], floor: float | None) -> ViewValues:
    posed = [r for r in records if "point_info" in r.files]
    infos = [json.loads(store.get_bytes(r.files["point_info"].key)) for r in posed]
    keys = [(r.point, r.view) for r in posed]
    if not infos:
        return {}
    from services.datasets.dataset import camera_of  # the one reading of a point_info's camera

    W = np.stack([camera_of(i)[1] for i in infos]).astype(np.float64)
    low = min(float(i["point_location"][2]) for i in infos) if floor is None else floor
    values = camera_distributions(W, np.array([i["field_of_view_rads"] for i in infos]), low)
    values["distance_m"] = np.array([i.get("camera_distance", np.nan) for i in infos], dtype=np.float64)
    values["obliqueness_deg"] = np.degrees([i.get("obliqueness_angle", np.nan) for i in infos])
    counts: dict[int, int] = {}
    for point, _ in keys:
        counts[point] = counts.get(point, 0) + 1
    return {k: {**{n: float(values[n][j]) for n in values}, "views_per_point": float(counts[k[0]])}
            for j, k in enumerate(keys)}


def keep_in_ranges(store: ObjectStore, job: JobDocument | None, records: list[ViewRecord],
                   where: Ranges) -> list[ViewRecord]:
    """The records whose values lie in every range of `where` (bounds included; a view without a value for a
    filtered distribution is left out)."""
    check_ranges(where)
    by_space: dict[str, list[ViewRecord]] = {}
    for r in records:
        by_space.setdefault(r.space, []).append(r)
    kept: set[tuple[str, int, int]] = set()
    for space, members in by_space.items():
        record = _space_record(job, space)
        key = record.get("plan")
        values = _from_plan(store, key, _floor(record)) if isinstance(key, str) and key else None
        if values is None:
            values = _from_point_info(store, members, _floor(record))
        for r in members:
            v = values.get((r.point, r.view))
            if v is not None and all(lo <= v.get(n, np.nan) <= hi for n, (lo, hi) in where.items()):
                kept.add((r.space, r.point, r.view))
    return [r for r in records if (r.space, r.point, r.view) in kept]
