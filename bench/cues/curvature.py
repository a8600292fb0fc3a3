"""Benchmark: the per-vertex curvature a worker computes once per space (issue 20: part of every run's
start-up), on the real rooms at the default radius, one core: the grid neighbour search against the k-d tree
search it replaced on rooms (the same estimator with services.worker.inputs.curvature.GRID_MAX_BALL = 0, which
sends every mesh to the tree), interleaved, CPU seconds (medians of --repeats), and whether the two give the
same array bit for bit. With --against REV, also the estimator as it was at git revision REV (its module
loaded from `git show`, compiled before the timing), interleaved with today's: an A/B of a change on the same
host and moment. Writes bench/results/curvature.json (the previous run's figures kept under "before").
Run: .venv/bin/python bench/cues/curvature.py [--repeats 5] [--against REV]
"""

from __future__ import annotations

import os

if hasattr(os, "sched_setaffinity"):  # one core, before numpy/numba start their pools
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.ab import module_at, write_keeping_before  # noqa: E402
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.rooms import ROOMS  # noqa: E402
from bench.render.room_cost import cpu_model, load  # noqa: E402
from services.core.domain.jobspec import CueParams  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from services.worker.inputs import curvature  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "curvature.json"


def timed(mesh: object, radius: float, grid_max_ball: float) -> tuple[float, np.ndarray]:
    """CPU seconds and result of one principal_curvatures call with the given search threshold."""
    saved, curvature.GRID_MAX_BALL = curvature.GRID_MAX_BALL, grid_max_ball
    try:
        t0 = time.process_time()
        out = curvature.principal_curvatures(mesh, radius)  # type: ignore[arg-type]
        return time.process_time() - t0, out
    finally:
        curvature.GRID_MAX_BALL = saved


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--against", default="", help="a git revision whose estimator is timed beside today's")
    ap.add_argument("--rooms", default=",".join(ROOMS), help="comma-separated: " + ",".join(ROOMS))
    args = ap.parse_args()
    radius = CueParams().curvature_radius_m
    result: dict = {
        "radius_m": radius, "clock": "process CPU seconds, one core, medians",
        "machine": f"{os.cpu_count()} cores ({cpu_model()}), shared", "load_before": load(), "rooms": {},
    }
    with tempfile.TemporaryDirectory(prefix="omnidata-curvature-") as tmp:
        old = (
            module_at(args.against, "services/worker/inputs/curvature.py", Path(tmp))
            if args.against
            else None
        )
        for room in args.rooms.split(","):
            path, frame = ROOMS[room]
            mesh = load_space(path, **frame).mesh
            # numba kernels loaded (or compiled) outside the timing
            timed(mesh, radius, curvature.GRID_MAX_BALL)
            timed(mesh, radius, 0)
            if old is not None:
                old.principal_curvatures(mesh, radius)
            grid, tree, before = [], [], []
            for _ in range(args.repeats):
                g, a = timed(mesh, radius, curvature.GRID_MAX_BALL)
                t, b = timed(mesh, radius, 0)
                grid.append(g)
                tree.append(t)
                if old is not None:
                    t0 = time.process_time()
                    c = old.principal_curvatures(mesh, radius)
                    before.append(time.process_time() - t0)
            row = {"vertices": len(mesh.vertices), "faces": len(mesh.faces),
                   "grid_s": round(float(np.median(grid)), 3), "kd_tree_s": round(float(np.median(tree)), 3),
                   "bit_identical": bool(np.array_equal(a, b))}
            row["speedup"] = round(row["kd_tree_s"] / row["grid_s"], 2)
            if old is not None:
                row["against"] = {"rev": args.against, "s": round(float(np.median(before)), 3),
                                  "to_today": round(float(np.median(before)) / row["grid_s"], 2),
                                  "bit_identical": bool(np.array_equal(a, c))}
            result["rooms"][room] = row
            print(room, json.dumps(row), flush=True)
    result["load_after"] = load()
    write_keeping_before(RESULTS, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
