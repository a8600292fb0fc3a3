"""The designer page's warm process: plans a spec over stored spaces, renders a few small previews, and fits a
spec to a space's capture.

The API starts one (or a few) of these by name (services.core.named_call) and talks to it over a socket; it
stays up between requests with the loaded spaces, the last plans and a Blender scene in memory, so a knob
change costs a plan (tenths of a second on a room) and a few 96 px renders (milliseconds each), not the
seconds that importing Blender and building a scene take. The API waits for each answer within a time budget
and ends the process when it runs past it; the next request starts a fresh one.

Requests are (kind, payload) tuples, answers ("ok", result), ("invalid", message) for a spec the space cannot
meet, or ("error", message). Positions are world metres (+Z up); angles in the report are degrees.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections import OrderedDict
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, TypeVar

import numpy as np

from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import PlanError, SpacePlan
from services.core.ingest.errors import SpaceError
from services.core.ingest.loading import LoadedSpace

PREVIEW_CUES = ("rgb", "depth_zbuffer", "normal", "segment_unsup2d")
PREVIEW_PX = 96
MAX_DRAWN = (
    1500  # cameras, points and camera-point lines sent for the top and side views (a sample past that)
)
CACHED_SPACES = 4
CACHED_PLANS = 8
NICENESS = 5  # the API process serving other requests comes first
K = TypeVar("K")
V = TypeVar("V")


def _cached(cache: OrderedDict[K, V], key: K, make: Callable[[], V], size: int) -> V:
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    value = cache[key] = make()
    while len(cache) > size:
        cache.popitem(last=False)
    return value


@dataclasses.dataclass
class DesignState:
    """What the process keeps between requests: loaded spaces, plans, and one Blender scene."""

    spaces: OrderedDict[str, LoadedSpace] = dataclasses.field(default_factory=OrderedDict)
    plans: OrderedDict[str, SpacePlan] = dataclasses.field(default_factory=OrderedDict)
    floors: dict[str, float] = dataclasses.field(default_factory=dict)
    scene_key: str | None = None
    scene: Any = None  # services.worker.inputs.space_cache.SpaceContext once a preview was rendered

    def loaded(self, source: dict[str, Any], spec: JobSpec) -> tuple[str, LoadedSpace]:
        """(key, the space loaded in its stored frame) for a source sent by the API."""
        from services.scheduler.plan_space import load_for_job

        key = json.dumps([source["path"], source["checksum"], source["frame"]], sort_keys=True)
        return key, _cached(
            self.spaces, key, lambda: load_for_job(source["path"], spec, frame=source["frame"]), CACHED_SPACES
        )

    def plan(self, source: dict[str, Any], spec: JobSpec) -> tuple[str, LoadedSpace, SpacePlan]:
        """(space key, loaded space, its plan under `spec`), planned once per space and spec."""
        from services.scheduler.plan_space import plan_space

        key, loaded = self.loaded(source, spec)
        plan_key = json.dumps([key, source["name"], spec.model_dump(mode="json")], sort_keys=True)
        plan = _cached(self.plans, plan_key, lambda: plan_space(loaded, spec, source["name"]), CACHED_PLANS)
        return key, loaded, plan

    def floor_z(self, key: str, loaded: LoadedSpace) -> float:
        """Heights are measured above the scan's lowest floor (the bottom of its box when it has none), as
        the fit to a capture measures them."""
        from services.scheduler.planning.fit import floor_z

        if key not in self.floors:
            found = floor_z(loaded)
            self.floors[key] = float(np.asarray(loaded.bounds)[0][2]) if found is None else found
        return self.floors[key]

    def context(self, key: str, loaded: LoadedSpace) -> Any:
        """The Blender scene of a space: one at a time (a room's scene holds hundreds of MB)."""
        from services.worker.inputs.space_cache import SpaceContext

        if self.scene_key != key:
            if self.scene is not None:
                self.scene.close()
            self.scene, self.scene_key = SpaceContext.from_loaded(loaded, key=key[-64:]), key
        return self.scene


def _sample(n: int, most: int) -> np.ndarray:
    """Evenly spread indices into n items, at most `most` of them (the same ones for the same plan)."""
    return np.arange(n) if n <= most else np.linspace(0, n - 1, most).round().astype(int)


def _drawing(source: dict[str, Any], loaded: LoadedSpace, plan: SpacePlan) -> dict[str, Any]:
    """What the page draws of one space: bounds, a sample of cameras, points and camera-point lines."""
    cams = _sample(len(plan.cameras), MAX_DRAWN)
    points = _sample(len(plan.points), MAX_DRAWN)
    cam_at = {int(c): i for i, c in enumerate(cams)}
    point_at = {int(p): i for i, p in enumerate(points)}
    views_per_point = np.bincount([v.point_idx for v in plan.views], minlength=len(plan.points))
    lines = [
        [point_at[v.point_idx], cam_at[v.camera_idx]]
        for v in plan.views
        if v.point_idx in point_at and v.camera_idx in cam_at
    ]
    return {
        "id": source["id"],
        "name": source["name"],
        "shortfall": plan.shortfall,
        "counts": {"cameras": len(plan.cameras), "points": len(plan.points), "views": len(plan.views)},
        "bounds": np.round(np.asarray(loaded.bounds, dtype=float), 3).tolist(),
        "cameras": [np.round(plan.cameras[c].position, 3).tolist() for c in cams],
        "points": [[*np.round(plan.points[p].position, 3).tolist(), int(views_per_point[p])] for p in points],
        "lines": [lines[i] for i in _sample(len(lines), MAX_DRAWN)],
    }


def plan_report(state: DesignState, payload: dict[str, Any]) -> dict[str, Any]:
    """The plan of `payload["spec"]` over its spaces: per-space drawings, the distributions of all views."""
    from services.core.domain.steering import histograms, summary, view_distributions

    t0 = time.perf_counter()
    spec = JobSpec.model_validate(payload["spec"])
    drawn, values = [], []
    for source in payload["spaces"]:
        key, loaded, plan = state.plan(source, spec)
        drawn.append(_drawing(source, loaded, plan))
        values.append(view_distributions(plan, floor_z=state.floor_z(key, loaded)))
    merged = {name: np.concatenate([v[name] for v in values]) for name in values[0]} if values else {}
    return {
        "spaces": drawn,
        "histograms": histograms(merged),
        "summary": summary(merged),
        "planning_s": round(time.perf_counter() - t0, 3),
    }


def previews(state: DesignState, payload: dict[str, Any]) -> dict[str, Any]:
    """PNG previews (readable renderings) of `payload["count"]` views spread over the plan, PREVIEW_PX
    square."""
    from services.datasets.previews import png_bytes, preview_array
    from services.worker.executor import render_view_cues

    t0 = time.perf_counter()
    spec = JobSpec.model_validate(payload["spec"])
    planned = [state.plan(source, spec) for source in payload["spaces"]]
    every = [(i, view) for i, (_k, _l, plan) in enumerate(planned) for view in plan.views]
    out = []
    for at in _sample(len(every), int(payload["count"])) if every else []:
        i, view = every[at]
        key, loaded, plan = planned[i]
        small = dataclasses.replace(view, resolution=PREVIEW_PX)
        files = render_view_cues(state.context(key, loaded), small, PREVIEW_CUES, spec.params, plan=plan)
        out.append(
            {
                "space": payload["spaces"][i]["name"],
                "point": view.point_idx,
                "view": view.v,
                "fov_deg": round(float(np.degrees(view.fov)), 1),
                "images": {
                    cue: png_bytes(preview_array(cue, data, spec.params)) for cue, data in files.items()
                },
            }
        )
    return {"previews": out, "render_s": round(time.perf_counter() - t0, 3)}


def fit(state: DesignState, payload: dict[str, Any]) -> dict[str, Any]:
    """`payload["spec"]` fitted to the posed capture stored with the first space (its fov, pitch, height and
    roll), and the capture's histograms."""
    from services.core.domain.steering import histograms
    from services.core.ingest.targets import capture_target
    from services.scheduler.planning.fit import fit_spec, target_enclosed

    t0 = time.perf_counter()
    spec = JobSpec.model_validate(payload["spec"])
    source = payload["spaces"][0]
    key, loaded = state.loaded(source, spec)
    if loaded.capture is None:
        raise ValueError(
            f"space {source['name']!r} has no posed capture to fit to (upload one with the scan)"
        )
    floor = state.floor_z(key, loaded)
    target = capture_target(loaded.capture, floor)
    enclosed = target_enclosed(loaded, target.centres) if target.centres is not None else True
    result = fit_spec(
        loaded, spec, target.values, floor_z=floor, space_name=source["name"], rounds=4, enclosed=enclosed
    )
    return {
        "spec": result.spec.model_dump(mode="json"),
        "ks": result.ks,
        "target": histograms(target.values),
        "source": target.source,
        "frames": len(target.values["fov_deg"]),
        "fit_s": round(time.perf_counter() - t0, 3),
    }


def warm(_state: DesignState, _payload: dict[str, Any]) -> dict[str, Any]:
    """Import the planner, the cue code and Blender ahead of the first request (a few seconds, once)."""
    import services.scheduler.plan_space  # noqa: F401
    import services.worker.blender.scene  # noqa: F401
    import services.worker.executor  # noqa: F401

    return {"pid": os.getpid()}


HANDLERS: dict[str, Callable[[DesignState, dict[str, Any]], dict[str, Any]]] = {
    "plan": plan_report,
    "previews": previews,
    "fit": fit,
    "warm": warm,
}


def serve(conn: Connection) -> None:
    """Answer requests on `conn` until the API closes it."""
    os.nice(NICENESS)
    state = DesignState()
    while True:
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            return
        try:
            conn.send(("ok", HANDLERS[kind](state, payload)))
        except (PlanError, SpaceError, ValueError) as e:  # the spec cannot be met on these spaces
            conn.send(("invalid", str(e)))
        except Exception as e:  # noqa: BLE001 - reported to the page; the process stays up
            conn.send(("error", f"{type(e).__name__}: {e}"))
