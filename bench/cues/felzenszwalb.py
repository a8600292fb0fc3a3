"""Benchmark: the superpixels of the two unsupervised segmentations (Felzenszwalb's merge and min-size passes,
the segment cues' largest step) on real room views at 512 px, one core, CPU seconds per view (medians over
--repeats) of each whole segment cue (segment_unsup2d, segment_unsup25d: features, background fill,
superpixels, region graph, normalized cuts). With --against REV, the same with
services/worker/cues/felzenszwalb.py as it was at git revision REV swapped in, interleaved with today's, and
whether every label image is the same bit for bit. Views: bench/cues/derivations.py's (the planner's views of
each room, their pass sets rendered once and cached). Writes bench/results/felzenszwalb.json (the previous
run's figures kept under "before"). Run: .venv/bin/python bench/cues/felzenszwalb.py [--views 6] [--repeats 5]
[--against REV]
"""

from __future__ import annotations

import os

if hasattr(os, "sched_setaffinity"):  # one core, before numpy/numba start their pools
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
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
from services.worker.cues import segmentation  # noqa: E402
from services.worker.passes import ViewPasses  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "felzenszwalb.json"
CUES = {"segment_unsup2d": segmentation.segment_unsup2d, "segment_unsup25d": segmentation.segment_unsup25d}


def segment_view(passes: ViewPasses, felzenszwalb: type) -> tuple[dict[str, float], list[np.ndarray]]:
    """CPU seconds of each segment cue on one view (a fresh context: nothing shared from an earlier run) with
    `felzenszwalb` as the superpixel class, and the label images."""
    saved, segmentation.Felzenszwalb = segmentation.Felzenszwalb, felzenszwalb
    try:
        ctx = ViewContext(None, CueParams(), passes=passes)
        # edge_occlusion's (the 2.5d graph's input), made before the timing
        segmentation.occlusion_response(ctx)
        seconds, labels = {}, []
        for name, cue in CUES.items():
            t0 = time.process_time()
            labels.append(cue(ctx))
            seconds[name] = time.process_time() - t0
        return seconds, labels
    finally:
        segmentation.Felzenszwalb = saved


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--against", default="", help="a git revision whose felzenszwalb.py is timed beside today's"
    )
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    ap.add_argument("--rooms", default=",".join(ROOMS), help="comma-separated: " + ",".join(ROOMS))
    args = ap.parse_args()
    keep_freed_memory()  # as a worker: freed arrays are reused, not faulted in afresh each view
    result: dict = {
        "resolution": 512, "clock": "process CPU seconds per view, one core, medians",
        "machine": f"{os.cpu_count()} cores ({cpu_model()}), shared", "load_before": load(), "rooms": {},
    }
    with tempfile.TemporaryDirectory(prefix="omnidata-felzenszwalb-") as tmp:
        sides = {"this": segmentation.Felzenszwalb}
        if args.against:
            old = module_at(args.against, "services/worker/cues/felzenszwalb.py", Path(tmp))
            sides = {"against": old.Felzenszwalb, **sides}
        for room in args.rooms.split(","):
            passes = room_views(room, args.views, 512, args.cache)[0]
            times: dict[str, dict[str, list[float]]] = {side: {c: [] for c in CUES} for side in sides}
            same = True
            for side in sides.values():  # kernels compiled or loaded outside the timing
                segment_view(passes[0], side)
            for r in range(args.repeats):
                for p in passes:
                    order = list(sides) if r % 2 == 0 else list(sides)[::-1]  # neither side always runs first
                    labels = {}
                    for side in order:
                        seconds, labels[side] = segment_view(p, sides[side])
                        for c, s in seconds.items():
                            times[side][c].append(s)
                    if args.against:
                        same &= all(np.array_equal(a, b) for a, b in zip(labels["against"], labels["this"],
                                                                          strict=True))
            row: dict = {
                side: {c: round(float(np.median(v)), 4) for c, v in t.items()} for side, t in times.items()
            }
            if args.against:
                row["against_rev"] = args.against
                row["labels_bit_identical"] = bool(same)
                row["saved_s_per_view"] = round(sum(row["against"].values()) - sum(row["this"].values()), 4)
            result["rooms"][room] = row
            print(room, json.dumps(row), flush=True)
    result["load_after"] = load()
    write_keeping_before(RESULTS, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
