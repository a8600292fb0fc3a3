"""Benchmark: cost per view of the 3D augmentation cues (rgb_refocus, rgb_fog, rgb_motion_blur, rgb_flash) on
the real room (../shared/scenes/icl_livingroom, the planner's views, 512x512, default distributions), one
core.

Per view: a bare 1-sample render (the floor of any bpy renderer, as in bench/render/render.py), then one pass
render and the augmentation cues derived from it; each cue's exclusive CPU seconds (its value and its PNG
encoding; the inputs rgb/depth/reshading are timed apart, since a job that asks for augmentations has them
anyway), medians over views. Writes the key "augmentations" of bench/results/augment.json.
Run: .venv/bin/python bench/render/augment.py [--views 4] [--resolution 512]
"""

from __future__ import annotations

import os
import sys

if hasattr(os, "sched_setaffinity"):  # one core, as bench/render/render.py
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.render.render import ROOM, ROOM_NAME, room_plan  # noqa: E402
from services.core.domain.jobspec import CueParams  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from services.worker.executor import make_context, produce  # noqa: E402
from services.worker.inputs.space_cache import SpaceContext  # noqa: E402
from services.worker.passes import ViewGeometry  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402

RESULTS = results_dir()
AUGMENTATIONS = ("rgb_refocus", "rgb_fog", "rgb_motion_blur", "rgb_flash")
INPUTS = ("rgb", "depth_zbuffer", "depth_euclidean", "reshading", "augment_params")


def measure(n_views: int, resolution: int) -> dict:
    params = CueParams()
    loaded = load_space(ROOM)
    space = SpaceContext.from_loaded(loaded, key=ROOM_NAME)
    plan = room_plan(loaded, resolution)
    views = list(plan.views[:: max(1, len(plan.views) // n_views)][:n_views])
    cues = [*INPUTS, *AUGMENTATIONS]
    scene = space.scene()
    scene.render_floor(ViewGeometry.of(views[0]))  # warm the Cycles sessions before timing
    _ = make_context(space, views[0], cues, params, plan=plan).passes
    floor_s: list[float] = []
    per_cue: defaultdict[str, list[float]] = defaultdict(list)
    samples: list[int] = []
    for view in views:
        c0 = time.process_time()
        scene.render_floor(ViewGeometry.of(view))
        floor_s.append(time.process_time() - c0)
        ctx = make_context(space, view, cues, params, plan=plan)
        ctx.clock = time.process_time
        for c in cues:
            produce(c, ctx)
        for c in cues:
            per_cue[c].append(ctx.timings.get(f"cue:{c}", 0.0) + ctx.timings.get(f"encode:{c}", 0.0)
                              + (ctx.timings.get("augment_params", 0.0) if c == "augment_params" else 0.0))
        drawn = json.loads(produce("augment_params", ctx))
        samples.append(len(drawn))
    space.close()
    floor = float(np.median(floor_s))
    med = {c: round(float(np.median(v)), 4) for c, v in per_cue.items()}
    return {
        "scene": ROOM_NAME,
        "views": len(views),
        "resolution": resolution,
        "clock": "process CPU seconds (time.process_time), one core",
        "floor_s_median": round(floor, 4),
        "per_cue_s_median": {c: med[c] for c in AUGMENTATIONS},
        "per_cue_ratio_to_floor": {c: round(med[c] / floor, 3) for c in AUGMENTATIONS},
        "inputs_s_median": {c: med[c] for c in INPUTS},
        "note": "each augmentation's own cost; its inputs (rgb, depths, reshading, the drawn parameters) are "
                "listed apart. Machine shared with other developers' work while measured.",
    }


def main() -> int:
    keep_freed_memory()  # the worker's heap settings (services.worker.process.heap): timings as a worker's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--out", type=Path, default=RESULTS / "augment.json")
    args = ap.parse_args()
    figures = measure(args.views, args.resolution)
    doc = json.loads(args.out.read_text()) if args.out.exists() else {}
    doc["augmentations"] = figures
    args.out.write_text(json.dumps(doc, indent=1) + "\n")  # the file's own layout
    print(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
