"""Benchmark: the segment cues' background fill (every pixel off the surface takes its nearest surface pixel's
features: services.worker.cues.feature_transform.nearest_site, then segmentation._gather) on real room views
at 512 px, one core, against the two modules as they were at git revision --against, interleaved.

Per view (bench/cues/derivations.py's views: the planner's views of each room, their pass sets rendered once
and cached): the nearest sites of the surface mask, and the gather of the 2.5d feature image (4 channels) at
them; each side's best of --repeats runs (the kernels take a few ms, so the best run is the one the host did
not disturb), and whether both sides give the same arrays bit for bit. A view pays one nearest-site search
(the two segmentations share it) and one gather per segmentation whose feature image is not one colour.
Writes bench/results/background_fill.json (the previous run kept under "before").
Run: .venv/bin/python bench/cues/background_fill.py [--against REV] [--views 6] [--repeats 7]
"""

from __future__ import annotations

import os

if hasattr(os, "sched_setaffinity"):  # one core, before numpy/numba start their pools
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.cues.derivations import room_views  # noqa: E402
from bench.lib.ab import module_at, write_keeping_before  # noqa: E402
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.rooms import ROOMS  # noqa: E402
from bench.render.room_cost import cpu_model, load  # noqa: E402
from services.core.domain.jobspec import CueParams  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.cues import feature_transform, registry, segmentation  # noqa: E402
from services.worker.cues.common import valid  # noqa: E402

RESULTS = results_dir() / "background_fill.json"


def best_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times) * 1e3


def old_gather(old_seg: object, features: np.ndarray, mask: np.ndarray, iy: np.ndarray,
               ix: np.ndarray) -> np.ndarray:
    """The revision's gather, whichever signature it has (before: features, iy, ix)."""
    try:
        return old_seg._gather(features, mask, iy, ix)  # type: ignore[attr-defined]
    except TypeError:
        return old_seg._gather(features, iy, ix)  # type: ignore[attr-defined]


def time_view(mask: np.ndarray, features: np.ndarray, sites: tuple[np.ndarray, np.ndarray], old_ft: object,
              old_seg: object, repeats: int) -> dict[str, float]:
    """Best-of-repeats ms of each side's nearest-site search and gather (both gathers at the same sites)."""
    sides = {
        "against": (old_ft.nearest_site, lambda: old_gather(old_seg, features, mask, *sites)),  # type: ignore[attr-defined]
        "this": (feature_transform.nearest_site, lambda: segmentation._gather(features, mask, *sites)),
    }
    out = {}
    for side, (nearest, gather) in sides.items():
        out[f"nearest_ms_{side}"] = round(best_ms(lambda nearest=nearest: nearest(mask), repeats), 3)
        out[f"gather_ms_{side}"] = round(best_ms(gather, repeats), 3)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--against", default="6a8582c",
        help="the git revision before the change (default: the one "
        "before the fill gathered only the pixels off the surface)",
    )
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--rooms", default=",".join(ROOMS))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    args = ap.parse_args()
    cues = dict(registry.REGISTRY)
    with tempfile.TemporaryDirectory(prefix="omnidata-fill-ab-") as tmp:
        old_ft = module_at(args.against, "services/worker/cues/feature_transform.py", Path(tmp))
        # the revision's module registers its cues again: today's stay the registered ones
        registry.REGISTRY.clear()
        old_seg = module_at(args.against, "services/worker/cues/segmentation.py", Path(tmp))
        registry.REGISTRY.clear()
        registry.REGISTRY.update(cues)
    result: dict = {
        "against": args.against, "resolution": 512, "clock": "wall ms, best of the repeats, one core",
        "machine": cpu_model(), "load_before": load(), "rooms": {},
    }
    for room in args.rooms.split(","):
        passes, plan, views = room_views(room, args.views, 512, args.cache)
        rows = []
        for p, v in zip(passes, views, strict=True):
            ctx = ViewContext(v, CueParams(), passes=p, plan=plan)
            mask = np.ascontiguousarray(valid(ctx), dtype=bool)
            features = segmentation.features25d(ctx)
            old_sites, new_sites = old_ft.nearest_site(mask), feature_transform.nearest_site(mask)
            same = all(np.array_equal(a, b) for a, b in zip(old_sites, new_sites, strict=True))
            same &= np.array_equal(old_gather(old_seg, features, mask, *old_sites).view(np.uint32),
                                   segmentation._gather(features, mask, *new_sites).view(np.uint32))
            row = {"off_surface_share": round(float((~mask).mean()), 3), "identical": bool(same),
                   **time_view(mask, features, new_sites, old_ft, old_seg, args.repeats)}
            rows.append(row)
        summary = {
            k: round(float(np.median([r[k] for r in rows])), 3)
            for k in rows[0]
            if k.endswith("_ms_this") or k.endswith("_ms_against")
        }
        summary["identical_views"] = f"{sum(r['identical'] for r in rows)} of {len(rows)}"
        result["rooms"][room] = {"median": summary, "views": rows}
        print(room, summary)
    result["load_after"] = load()
    write_keeping_before(RESULTS, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
