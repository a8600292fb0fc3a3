"""Benchmark: storing a view's outputs in the local object folder (LocalStore.put_many: every file a worker
writes for a view, flushed to disk and checksummed, kept out of the page cache as a worker asks), what each
view of `generate` pays after its derivations, one core.
The files: every default cue of one real view of the 7-Scenes kitchen (bench/cues/derivations.py's views;
~6 MB), stored --views times under fresh names in folders that exist (as a job's views after its first); wall
and CPU seconds per view (medians and 75th percentiles). With --against REV, also
services/core/storage/local.py as it was at git revision REV, interleaved view by view with today's in its own
folder. Writes bench/results/store_put.json (the previous run's figures kept under "before").
Run: .venv/bin/python bench/output/store_put.py [--views 40] [--against REV]
     [--folder DIR (default: the system's temp)]
"""

from __future__ import annotations

import os

if hasattr(os, "sched_setaffinity"):  # one core, as the room benchmarks' worker
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import argparse  # noqa: E402
import inspect  # noqa: E402
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
from bench.render.room_cost import cpu_model, load  # noqa: E402
from services.core.domain.cues import default_cues  # noqa: E402
from services.core.domain.jobspec import CueParams  # noqa: E402
from services.core.domain.keys import output_key  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.executor import produce  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "store_put.json"
ROOM = "7scenes_redkitchen"


def view_files(cache: Path) -> list[tuple[str, bytes]]:
    """(cue, bytes) of every default cue of one real view of the kitchen."""
    passes, plan, views = room_views(ROOM, 2, 512, cache)
    ctx = ViewContext(views[0], CueParams(), passes=passes[0], plan=plan)
    return [(cue, produce(cue, ctx)) for cue in default_cues(has_semantics=False)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--against", default="", help="a git revision whose local.py is timed beside today's")
    ap.add_argument(
        "--folder", type=Path, default=None, help="where the stores' folders go (a temp folder in it)"
    )
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    args = ap.parse_args()
    files = view_files(args.cache)
    result: dict = {
        "files_per_view": len(files), "bytes_per_view": sum(len(d) for _, d in files),
        "clock": "seconds per view, one core (CPU: the process's, the flushing threads' included)",
        "machine": f"{os.cpu_count()} cores ({cpu_model()}), shared", "load_before": load(),
    }
    with tempfile.TemporaryDirectory(prefix="omnidata-store-put-", dir=args.folder) as tmp:
        classes = {"this": LocalStore}
        if args.against:
            classes = {
                "against": module_at(args.against, "services/core/storage/local.py", Path(tmp)).LocalStore,
                **classes,
            }
        stores = {side: cls(Path(tmp) / side) for side, cls in classes.items()}
        wall: dict[str, list[float]] = {side: [] for side in stores}
        cpu: dict[str, list[float]] = {side: [] for side in stores}
        for v in range(-1, args.views):  # view -1 makes the folders, as a job's first view: not timed
            order = list(stores) if v % 2 == 0 else list(stores)[::-1]
            for side in order:
                items = [(output_key(cue, "omnidata", ROOM, v + 1, 0), data) for cue, data in files]
                hint = (
                    {"keep_cached": False}
                    if "keep_cached" in inspect.signature(stores[side].put_many).parameters
                    else {}
                )
                t0, c0 = time.perf_counter(), time.process_time()
                stores[side].put_many(items, **hint)
                if v >= 0:
                    wall[side].append(time.perf_counter() - t0)
                    cpu[side].append(time.process_time() - c0)
        for side in stores:
            result[side] = {"wall_s_median": round(float(np.median(wall[side])), 4),
                            "wall_s_p75": round(float(np.percentile(wall[side], 75)), 4),
                            "cpu_s_median": round(float(np.median(cpu[side])), 4)}
        if args.against:
            result["against_rev"] = args.against
            result["wall_saved_s_median"] = round(
                result["against"]["wall_s_median"] - result["this"]["wall_s_median"], 4
            )
    result["load_after"] = load()
    print(json.dumps(result, indent=1))
    write_keeping_before(RESULTS, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
