"""Benchmark: `generate --render-workers R` against every worker rendering, on the CPU cores of this machine
(issue 20).

With R renderers, the other workers only derive, from the pass sets the renderers store: the layout a GPU
needs (one device context, every core deriving). On CPU cores `generate` lets every worker render by default:
this benchmark showed the split slower there (1.27-1.46x on a 180-view job). The split costs the hand-off (a
renderer writes each pass set, a deriver reads it back) and saves every worker's Blender start-up and scene.
This measures that cost where it can be measured without a GPU: each room at 512 px, every default cue, a
worker per core, the two settings interleaved per repeat (so a neighbour's load moves both): wall time end to
end, task seconds per view by cue (the job's task rows), the stored pass set's size, and the timeline
(bench/render/room_cost.py: when each worker took its first task). Figures go to
bench/results/render_workers.json.
Run: .venv/bin/python bench/render/render_workers.py [--rooms icl_livingroom] [--points 14] [--repeats 2]
[--render-workers 1]
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import room_cost  # noqa: E402

from bench.lib.results import results_dir  # noqa: E402

RESULTS = results_dir() / "render_workers.json"


def run(room: str, cores: str, out: Path, spec: Path, render_workers: int | None) -> dict:
    space, extra = room_cost.ROOMS[room]
    if render_workers is not None:
        extra = [*extra, "--render-workers", str(render_workers)]
    result = room_cost.generate(space, extra, cores, out, spec, None)
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        size, renderers = db.execute(
            "SELECT AVG(size), COUNT(DISTINCT worker_id) FROM task WHERE cue = 'passes' AND state = 'done'"
        ).fetchone()
    # 0: every view batch derived its own pass set
    result["pass_set_stored_mb"] = round((size or 0) / 2**20, 2)
    result["workers_that_rendered"] = renderers
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", default="icl_livingroom,7scenes_redkitchen")
    ap.add_argument("--points", type=int, default=14, help="points per room (x 3 views)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--render-workers", type=int, default=1)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    cores = ",".join(str(c) for c in sorted(os.sched_getaffinity(0)))
    result: dict = {"cores": cores, "resolution": 512, "render_workers": args.render_workers, "rooms": {},
                    "clock": "wall seconds; task seconds from the job's task rows"}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="omnidata-renderworkers-") as tmp:
        spec = Path(tmp) / "spec.json"
        spec.write_text(
            json.dumps({"points": {"count": args.points, "max_views": 3}, "views": {"resolution": 512}})
        )
        for room in args.rooms.split(","):
            runs: dict[str, list[dict]] = {"every_worker_renders": [], "split": []}
            for i in range(args.repeats):
                runs["every_worker_renders"].append(
                    run(room, cores, Path(tmp) / f"{room}-{i}-all", spec, len(cores.split(",")))
                )
                runs["split"].append(
                    run(room, cores, Path(tmp) / f"{room}-{i}-split", spec, args.render_workers)
                )
                print(room, i, json.dumps({k: {f: v[-1][f] for f in ("wall_s", "task_s_per_view_total")}
                                           for k, v in runs.items()}), flush=True)
            summary = {
                k: {
                    "wall_s": [r["wall_s"] for r in v],
                    "task_s_per_view_total": [r["task_s_per_view_total"] for r in v],
                }
                for k, v in runs.items()
            }
            extra_task_s = [round(s["task_s_per_view_total"] - a["task_s_per_view_total"], 4)
                            for a, s in zip(runs["every_worker_renders"], runs["split"], strict=True)]
            result["rooms"][room] = {
                "runs": runs, "summary": summary, "hand_off_task_s_per_view": extra_task_s,
                "split_to_every_worker_wall": [
                    round(s["wall_s"] / a["wall_s"], 2)
                    for a, s in zip(runs["every_worker_renders"], runs["split"], strict=True)
                ],
            }
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(
        json.dumps(
            {room: {k: v for k, v in r.items() if k != "runs"} for room, r in result["rooms"].items()},
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
